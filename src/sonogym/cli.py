"""The ``sonogym`` command. Each subcommand is a thin wrapper over a library function."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

app = typer.Typer(
    help="SonoGym: robotic-ultrasound simulation on plain PyTorch.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


@app.callback()
def _root() -> None:
    """SonoGym: robotic-ultrasound simulation on plain PyTorch."""


@app.command()
def phantom(
    seed: Annotated[int, typer.Option(help="Phantom seed (anatomy varies with it).")] = 0,
    out: Annotated[
        Path, typer.Option(help="Folder to write the TotalSegmentator layout to.")
    ] = Path("runs/phantom"),
    spacing: Annotated[float, typer.Option(help="Isotropic voxel size in mm (0.5-2.0).")] = 1.0,
    preview: Annotated[bool, typer.Option(help="Also write preview.png.")] = True,
    combined: Annotated[
        bool, typer.Option(help="Write one combined label map instead of per-class masks.")
    ] = False,
) -> None:
    """Build a procedural lumbar phantom and write ct.nii.gz + segmentations/ (+ preview.png)."""
    from sonogym.anatomy import PhantomParams, load_phantom, save_totalsegmentator

    patient = load_phantom(seed, PhantomParams(spacing=spacing * 1e-3))
    save_totalsegmentator(patient, out, combined=combined)
    typer.echo(f"wrote {patient.name} ({'x'.join(map(str, patient.shape))} voxels) to {out}/")
    if preview:
        from sonogym.anatomy.preview import save_preview

        path = save_preview(patient, out / "preview.png")
        typer.echo(f"wrote {path}")


@app.command()
def demo(
    out: Annotated[Path, typer.Option(help="Folder for frames, videos and metrics.")] = Path(
        "runs/demo"
    ),
    envs: Annotated[int, typer.Option(help="Envs per task.")] = 4,
    seed: Annotated[int, typer.Option(help="Episode seed.")] = 0,
) -> None:
    """Run every task's expert on the default phantom; write frames, a video and metrics."""
    from sonogym.evaluation.demo import run_demo

    run_demo(out, num_envs=envs, seed=seed, log=typer.echo)


def main() -> None:
    app()


if __name__ == "__main__":
    main()
