"""The ``sonogym`` command. Each subcommand is a thin wrapper over a library function."""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import inspect
import typing
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Annotated, Any

import typer

from sonogym.agents.options import RunOptions

app = typer.Typer(
    help="SonoGym: robotic-ultrasound simulation on plain PyTorch.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


@app.callback()
def _root() -> None:
    """SonoGym: robotic-ultrasound simulation on plain PyTorch."""


#: The ``options`` parameter's placeholder default (``with_options`` replaces it by the flags).
ALL_DEFAULTS = RunOptions()


def with_options(cls: type) -> Callable[[Callable], Callable]:
    """Command decorator: the command's ``options`` parameter becomes one flag per field of
    the dataclass ``cls`` (the field's ``help`` metadata is the flag's help text), and the
    command receives them back as one ``cls``. Commands that share ``cls`` share the flags."""
    hints = typing.get_type_hints(cls)
    fields = dataclasses.fields(cls)
    flags = [
        inspect.Parameter(
            f.name,
            inspect.Parameter.POSITIONAL_OR_KEYWORD,
            default=f.default,
            annotation=Annotated[hints[f.name], typer.Option(help=f.metadata["help"])],
        )
        for f in fields
    ]

    def decorate(command: Callable) -> Callable:
        sig = inspect.signature(command, eval_str=True)
        params: list[inspect.Parameter] = []
        for p in sig.parameters.values():
            params.extend(flags if p.name == "options" else [p])

        @functools.wraps(command)
        def run(**kwargs: Any) -> Any:
            options = cls(**{f.name: kwargs.pop(f.name) for f in fields})
            if getattr(options, "simulator", None) is not None:
                name = _simulator_name(command.__name__.replace("_", "-"), options.simulator)
                options = dataclasses.replace(options, simulator=name)
            return command(options=options, **kwargs)

        run.__signature__ = sig.replace(parameters=params)  # type: ignore[attr-defined]
        run.__annotations__ = {p.name: p.annotation for p in params}
        return run

    return decorate


def _simulator_name(command: str, name: str | None) -> str | None:
    """``name``, or the current name of a simulator's former name, said in one line on stderr
    (the former names are removed in the version the note gives)."""
    if name is None:
        return None
    from sonogym.ultrasound.registry import alias_note, canonical_name, is_alias

    if not is_alias(name):
        return name
    typer.echo(f"sonogym {command}: {alias_note(name)}", err=True)
    return canonical_name(name, warn=False)


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
    force: Annotated[
        bool,
        typer.Option(help="Replace a subject folder that sonogym phantom wrote in --out."),
    ] = False,
) -> None:
    """Build a procedural lumbar phantom and write ct.nii.gz + segmentations/ (+ preview.png).
    An existing --out is never mixed into: it is refused unless --force replaces it, which it
    does only for a folder sonogym phantom wrote (its .sonogym marker) holding nothing else."""
    from sonogym.anatomy import PhantomParams, load_phantom, save_totalsegmentator
    from sonogym.runs import deleted_message, prepare_output

    with prepare_output(out, resume=False, force=force, kind="subject") as folder:
        if folder.deleted:
            typer.echo(deleted_message(out, folder.deleted))
        patient = load_phantom(seed, PhantomParams(spacing=spacing * 1e-3))
        save_totalsegmentator(patient, out, combined=combined)
        typer.echo(f"wrote {patient.name} ({'x'.join(map(str, patient.shape))} voxels) to {out}/")
        if preview:
            from sonogym.viz.preview import save_preview

            path = save_preview(patient, out / "preview.png")
            typer.echo(f"wrote {path}")


@app.command()
def image(
    seed: Annotated[int | None, typer.Option(help="Phantom seed (default 0).")] = None,
    patient: Annotated[
        Path | None,
        typer.Option(help="TotalSegmentator subject folder (ct.nii.gz + segmentations/)."),
    ] = None,
    pose: Annotated[
        list[str] | None,
        typer.Option(
            help="Surface pose 'x,z,yaw[,tilt]': x, z in mm in the patient frame (x right, "
            "z superior), yaw and tilt in rad (yaw 3.1416 transverse, 1.5708 sagittal). "
            "Repeatable. Default: above L4, transverse and sagittal."
        ),
    ] = None,
    us_model: Annotated[
        str | None,
        typer.Option(
            help="Ultrasound simulator: physical (default), reference, both (the two "
            "model-based models) or another registered one."
        ),
    ] = None,
    sheet: Annotated[
        bool, typer.Option(help="One sheet: CT slice | label slice | US per pose.")
    ] = False,
    probe: Annotated[str, typer.Option(help="linear (2-D) or volume (3-D, 5 slices).")] = "linear",
    spacing: Annotated[
        float, typer.Option(help="Voxel size in mm for the phantom / patient.")
    ] = 1.0,
    out: Annotated[Path, typer.Option(help="Folder for the PNGs.")] = Path("runs/image"),
) -> None:
    """Render ultrasound images at surface poses of a phantom or a patient folder, to PNG."""
    from sonogym.viz.render import parse_pose, render_command

    us_model = _simulator_name("image", us_model) or "physical"
    if us_model != "both":
        from sonogym.ultrasound.registry import get_simulator

        with _bad_parameter():
            get_simulator(us_model)  # an unknown name is refused before any work
    if seed is not None and patient is not None:
        raise typer.BadParameter("give --seed or --patient, not both")
    try:
        poses = [parse_pose(p) for p in pose or []]
    except ValueError as e:
        raise typer.BadParameter(str(e)) from e
    if patient is not None:
        from sonogym.anatomy import load_totalsegmentator

        subject = load_totalsegmentator(patient, spacing=spacing * 1e-3)
    else:
        from sonogym.anatomy import PhantomParams, load_phantom

        subject = load_phantom(seed or 0, PhantomParams(spacing=spacing * 1e-3))
    for path in render_command(subject, poses, us_model, sheet, probe, out):
        typer.echo(f"wrote {path}")


@app.command()
def morphometry(
    out: Annotated[
        Path, typer.Option(help="Folder for population.json, morphometry.md and comparison.png.")
    ] = Path("docs/results/morphometry"),
    subject: Annotated[
        Path | None,
        typer.Option(
            help="Real TotalSegmentator subject folder (ct.nii.gz + segmentations/); default: "
            "the example subject that ships with sonogym."
        ),
    ] = None,
    seeds: Annotated[int, typer.Option(help="Phantoms in the population (seeds 0, 1, ...).")] = 40,
    spacing: Annotated[float, typer.Option(help="Phantom voxel size in mm (0.5-2.0).")] = 2.0,
    subject_spacing: Annotated[
        float, typer.Option(help="Voxel size in mm the real subject is loaded at (0.25-5).")
    ] = 1.0,
    doc: Annotated[
        Path | None,
        typer.Option(
            help="Also rewrite the table between the morphometry marks of this "
            "markdown file (e.g. docs/anatomy.md)."
        ),
    ] = None,
) -> None:
    """Measure a phantom population and a real subject the same way (spine morphometry, soft
    tissue depths, bone-hit and skin-to-muscle profiles at the L4 goal views) and write the
    comparison. Every option is checked before anything is measured; a run that fails or is
    interrupted leaves no file of its own."""
    from sonogym.outputs import check_folder, undo_on_failure
    from sonogym.package_data import data_path, example_subject
    from sonogym.viz.morphometry import check_report, write_report

    _check_positive(("--seeds", seeds))
    folder = example_subject() if subject is None else Path(data_path(subject))
    with _bad_parameter():
        check_report(folder, range(seeds), spacing * 1e-3, subject_spacing * 1e-3, doc)
    check_folder(out, "--out")
    shown = "the example subject shipped with sonogym" if subject is None else folder
    typer.echo(f"morphometry: {seeds} phantoms at {spacing:g} mm against {shown}; "
               f"writing to {out.absolute()}/")  # fmt: skip
    cmd = (f"sonogym morphometry --out {out}" + (f" --subject {subject}" if subject else "")
           + f" --seeds {seeds} --spacing {spacing:g} --subject-spacing {subject_spacing:g}"
           + (f" --doc {doc}" if doc else ""))  # fmt: skip
    names = ("population.json", "morphometry.md", "comparison.png")
    with undo_on_failure(*(out / n for n in names)):
        paths = write_report(out, folder, range(seeds), spacing * 1e-3, subject_spacing * 1e-3,
                             doc=doc, command=cmd, log=typer.echo)  # fmt: skip
    for path in paths.values():
        typer.echo(f"wrote {path}")


@app.command()
def demo(
    out: Annotated[Path, typer.Option(help="Folder for frames, videos and metrics.")] = Path(
        "runs/demo"
    ),
    envs: Annotated[int, typer.Option(help="Envs per task.")] = 4,
    seed: Annotated[int, typer.Option(help="Episode seed.")] = 0,
    patient: Annotated[
        list[str] | None,
        typer.Option(
            help="A TotalSegmentator subject folder (ct.nii.gz + segmentations/) or a phantom "
            "seed; repeatable (default: phantom 0)."
        ),
    ] = None,
    task: Annotated[
        list[str] | None, typer.Option(help="Only this task; repeatable (default: all).")
    ] = None,
) -> None:
    """Run every task's expert on the default phantom or your own subjects; write frames, a
    video and metrics per task."""
    from sonogym.evaluation.demo import run_demo

    _check_positive(("--envs", envs))
    pats = parse_patients(patient)
    run_demo(out, num_envs=envs, seed=seed, tasks=tuple(task) if task else None, patients=pats,
             log=typer.echo)  # fmt: skip


def _rl_algorithms() -> str:
    """The registered RL algorithms and the tasks each trains on, for train's and sweep's
    help: "ppo, a2c (all tasks); ppo-sf, ppo-lag (surgery)."."""
    from sonogym.agents.algorithms import algorithm_names, task_algorithms
    from sonogym.envs.registry import task_names

    tasks, groups = task_names(), {}
    for algo in algorithm_names():
        on = tuple(t for t in tasks if algo in task_algorithms(t))
        groups.setdefault(on, []).append(algo)
    return (
        "; ".join(
            f"{', '.join(algos)} ({'all tasks' if on == tasks else ', '.join(on)})"
            for on, algos in groups.items()
        )
        + "."
    )


@app.command()
@with_options(RunOptions)
def train(
    task: Annotated[str, typer.Option(help="navigation, reconstruction or surgery.")],
    algo: Annotated[str, typer.Option(help=_rl_algorithms())] = "ppo",
    seed: Annotated[
        int | None, typer.Option(help="Seed of torch and the envs (default 0).")
    ] = None,
    options: RunOptions = ALL_DEFAULTS,
    env_option: Annotated[
        list[str] | None,
        typer.Option(
            help="Any other env option as KEY=VALUE (SI units, as the task's config names it), "
            "e.g. unsafe_penalty=0.5; repeatable. Overrides the preset's env options."
        ),
    ] = None,
    out: Annotated[
        Path | None, typer.Option(help="Run directory (default runs/<task>-<algo>-s<seed>).")
    ] = None,
    resume: Annotated[
        bool, typer.Option(help="Continue the run in --out from its last checkpoint.")
    ] = False,
    force: Annotated[bool, typer.Option(help="Replace an existing run in --out.")] = False,
    checkpoint_every: Annotated[
        int | None,
        typer.Option(help="Env steps per env between checkpoints (default: about ten in all)."),
    ] = None,
    protocol: Annotated[
        str | None,
        typer.Option(
            help="Train for an evaluation protocol: idt / odt-patient (cohort patients 0-4), "
            "odt-sim (also learned nets 0-3). --patients / --simulator override it."
        ),
    ] = None,
    set_: Annotated[
        list[str] | None,
        typer.Option(
            "--set",
            help="A training setting as KEY=VALUE, as sonogym sweep's grid names it: "
            "init_log_std, final_log_std, anneal_steps, reward_scale, ..., <algorithm>.<field> "
            "(ppo.learning_rate); repeatable. Applied last.",
        ),
    ] = None,
    init_from: Annotated[
        Path | None,
        typer.Option(
            help="Start from these weights instead of random ones (fine-tuning): a checkpoint "
            "RUN/checkpoints/agent_<t>.pt, or a shipped policy's name (sonogym eval --pretrained "
            "list), of the same task, network and observation. Its CPU time counts in this "
            "run's times.json."
        ),
    ] = None,
    dagger_expert: Annotated[
        str | None,
        typer.Option(
            help="Warm-start the policy by DAgger from this privileged expert before RL: "
            "'expert' (the task's) or a further one (navigation: 'level-counting'). Needs "
            "--dagger-steps; docs/agents.md."
        ),
    ] = None,
    dagger_steps: Annotated[
        int | None,
        typer.Option(help="Env steps per env of the DAgger warm start (8 rounds, beta 1 -> 0)."),
    ] = None,
) -> None:
    """Train an RL agent; TensorBoard logs, checkpoints and config.json go to the run directory.
    Settings resolve from the task's defaults, then the device preset, then these options."""
    from sonogym.agents.algorithms import check_algo
    from sonogym.agents.train import train as run_train
    from sonogym.evaluation.protocols import protocol_env_kwargs

    with _bad_parameter():
        check_algo(task, algo)
        options.check()
        _check_positive(("--checkpoint-every", checkpoint_every))
        pats, simulator = options.patient_specs(), options.simulator
        scene = options.scene_kwargs()
        env_kwargs = {**parse_env_options(task, env_option, scene), **scene}
        if protocol is not None:
            env_kwargs = protocol_env_kwargs(protocol, env_kwargs, pats, simulator)
            pats, simulator = None, None
        settings = parse_settings(set_)
        init_from = shipped_or_path(init_from)
        dagger = _dagger_option(task, dagger_expert, dagger_steps)
    res = run_train(
        task, algo, seed=seed, out=out, patients=pats, simulator=simulator,
        env_kwargs=env_kwargs, resume=resume, force=force, log=typer.echo,
        checkpoint_interval=checkpoint_every, settings=settings, init_from=init_from,
        dagger=dagger, **options.train_kwargs(),
    )  # fmt: skip
    typer.echo(f"trained {res.steps} steps; final checkpoint {res.checkpoint}")


@app.command()
def record(
    task: Annotated[str, typer.Option(help="navigation or surgery.")],
    out: Annotated[Path, typer.Option(help="Dataset folder (LeRobotDataset v3.0).")],
    recipe: Annotated[
        str | None,
        typer.Option(
            help="The paper's dataset recipe: navigation mb / lb / lb-4-nets; surgery mb / "
            "mb-5-patients / lb / lb-4-nets (simulator, nets, patients, starts, episodes)."
        ),
    ] = None,
    episodes: Annotated[
        int | None, typer.Option(help="Episodes to write (default: the recipe's, else 100).")
    ] = None,
    envs: Annotated[int | None, typer.Option(help="Parallel envs (default 16).")] = None,
    simulator: Annotated[
        str | None,
        typer.Option(
            help="physical, reference, learned or another registered simulator "
            "(overrides the recipe)."
        ),
    ] = None,
    learned_nets: Annotated[
        str | None, typer.Option(help="Comma-separated shipped net indices or generator.pt paths.")
    ] = None,
    patients: Annotated[
        list[str] | None, typer.Option(help="Phantom seed or subject folder; repeatable.")
    ] = None,
    phantom_spacing: Annotated[float | None, typer.Option(help="Phantom voxel size, mm.")] = None,
    seed: Annotated[int | None, typer.Option(help="Seed of the first batch (default 0).")] = None,
    resume: Annotated[bool, typer.Option(help="Continue an interrupted recording.")] = False,
    force: Annotated[bool, typer.Option(help="Replace an existing dataset in --out.")] = False,
) -> None:
    """Record the task's expert into a LeRobotDataset v3.0 folder (PNG frames in parquet),
    for imitation learning (sonogym il-train) and for LeRobot itself."""
    from sonogym.imitation.record import record as run_record

    _check_positive(("--episodes", episodes), ("--envs", envs))
    simulator = _simulator_name("record", simulator)
    scene = RunOptions(simulator=simulator, learned_nets=learned_nets, patients=patients,
                       phantom_spacing=phantom_spacing)  # fmt: skip
    with _bad_parameter():
        kw = scene.env_kwargs()
    run_record(task, out, episodes=episodes, recipe=recipe, envs=envs, env_kwargs=kw or None,
               seed=seed, resume=resume, force=force, log=typer.echo)  # fmt: skip


def _il_policies() -> str:
    """The registered imitation-learning policies, for il-train's help."""
    from sonogym.imitation.policies.registry import policy_names

    return " or ".join(policy_names())


@app.command("il-train")
def il_train(
    policy: Annotated[str, typer.Option(help=f"{_il_policies()}.")],
    data: Annotated[Path, typer.Option(help="Dataset folder (sonogym record).")],
    out: Annotated[Path, typer.Option(help="Run folder (checkpoints, config.json, tb/).")],
    steps: Annotated[int | None, typer.Option(help="Optimiser steps in total.")] = None,
    size: Annotated[
        str | None,
        typer.Option(help="Policy size: cpu (default, documented) or paper (LeRobot's)."),
    ] = None,
    batch_size: Annotated[int | None, typer.Option(help="Samples per step (default 8).")] = None,
    image_size: Annotated[
        str | None,
        typer.Option(help="HxW px the images are resampled to (e.g. 100x75); default: as stored."),
    ] = None,
    seed: Annotated[
        int | None, typer.Option(help="Seed of init, sample order and noise (default 1000).")
    ] = None,
    threads: Annotated[int | None, typer.Option(help="torch CPU threads.")] = None,
    device: Annotated[str, typer.Option(help="cpu or cuda[:i].")] = "cpu",
    resume: Annotated[
        bool,
        typer.Option(help="Continue the run in --out (options left out: the run's)."),
    ] = False,
    force: Annotated[bool, typer.Option(help="Replace an existing run in --out.")] = False,
    checkpoint_every: Annotated[
        int, typer.Option(help="Optimiser steps between checkpoints (a final one always).")
    ] = 5_000,
    checkpoint_minutes: Annotated[
        float,
        typer.Option(
            help="Also a checkpoint at least this often (minutes; 0: none), so a killed run "
            "resumes from at most this far back; each replaces the previous such one."
        ),
    ] = 5.0,
) -> None:
    """Train an imitation-learning policy (ACT, Diffusion Policy, ...) on an expert dataset;
    evaluate with sonogym eval --run."""
    from sonogym.agents.presets import cpu_threads
    from sonogym.imitation.run import read_run_config
    from sonogym.imitation.train import ILTrainConfig, il_train_settings, train_il

    _check_positive(("--steps", steps), ("--batch-size", batch_size),
                    ("--checkpoint-every", checkpoint_every))  # fmt: skip
    if not checkpoint_minutes >= 0:
        raise typer.BadParameter(
            f"--checkpoint-minutes must be >= 0 (0: none), got {checkpoint_minutes}"
        )
    old = read_run_config(out) if resume and (out / "config.json").is_file() else None
    with _bad_parameter():  # what is left out of a resumed run continues as it was trained
        settings = il_train_settings(policy, old, size=size, image_size=image_size, steps=steps,
                                     batch_size=batch_size, seed=seed)  # fmt: skip
    import torch

    torch.set_num_threads(
        threads or (cpu_threads() if device == "cpu" else torch.get_num_threads())
    )
    cfg = ILTrainConfig(data=str(data), out=str(out), device=device, resume=resume, force=force,
                        save_every=checkpoint_every, save_minutes=checkpoint_minutes,
                        **settings)  # fmt: skip
    res = train_il(cfg)
    typer.echo(f"trained {res.steps} steps (last loss {res.loss:.4f}) in {res.seconds:.0f} s; "
               f"evaluate with: sonogym eval --run {out}")  # fmt: skip


def _check_positive(*options: tuple[str, int | None]) -> None:
    """Refuse a given (not None) integer option below 1, naming it: none is silently
    defaulted."""
    for name, v in options:
        if v is not None and v < 1:
            raise typer.BadParameter(f"{name} must be a positive integer, got {v}")


@contextlib.contextmanager
def _bad_parameter() -> Iterator[None]:
    """A ``ValueError`` raised inside (an option's text or value refused by the library)
    becomes typer's usage error with the same message."""
    try:
        yield
    except ValueError as e:
        raise typer.BadParameter(str(e)) from None


def _dagger_option(task: str, expert: str | None, steps: int | None):
    """``--dagger-expert`` and ``--dagger-steps`` as a ``DaggerConfig`` (None: neither
    given); one without the other, an expert the task lacks or too few steps are refused."""
    if expert is None and steps is None:
        return None
    if expert is None or steps is None:
        raise ValueError("--dagger-expert and --dagger-steps go together: pass both, or neither")
    from sonogym.agents.dagger import DaggerConfig, check_expert

    check_expert(task, expert)
    if steps < 1:
        raise ValueError(f"--dagger-steps must be a positive integer, got {steps}")
    iterations = DaggerConfig.__dataclass_fields__["iterations"].default
    return DaggerConfig(expert, steps, iterations=min(iterations, steps))


def shipped_or_path(given: Path | None) -> Path | None:
    """``--init-from``: a shipped policy's name becomes its folder; a path stays as given."""
    if given is None or given.exists():
        return given
    from sonogym.evaluation.pretrained import available, pretrained_dir

    return pretrained_dir(str(given)) if str(given) in available() else given


def parse_settings(items: list[str] | None) -> dict[str, Any]:
    """``train --set KEY=VALUE`` items -> {key: value} (values as ``parse_value`` reads them);
    names a malformed item, a repeated key or an unknown setting."""
    from sonogym.agents.configs import check_setting_key
    from sonogym.envs.options import parse_value

    out: dict[str, Any] = {}
    for item in items or []:
        key, sep, value = (t.strip() for t in item.partition("="))
        if not sep or not key or not value:
            raise ValueError(f"--set {item!r}: write KEY=VALUE, e.g. final_log_std=-1.5")
        if key in out:
            raise ValueError(f"--set {key} is given twice")
        if key == "seed" or key.startswith("env."):
            raise ValueError(f"--set {key}: use --seed / --env-option for this")
        check_setting_key(key, "--set key")
        out[key] = parse_value(value)
    return out


#: Env options with their own ``train`` flag (units or parsing of their own there).
_FLAGGED_ENV_OPTIONS = {
    "obs_mode": "--obs-mode",
    "patients": "--patients",
    "simulator": "--simulator",
    "learned_nets": "--learned-nets",
    "phantom_spacing": "--phantom-spacing (in mm)",
    "device": "--device",
}


def parse_env_options(
    task: str, items: list[str] | None, flag_values: dict[str, Any] | None = None
) -> dict[str, Any]:
    """``--env-option KEY=VALUE`` items -> env keyword arguments
    (``sonogym.envs.options.parse_env_options``; the options with a flag of their own are
    refused, naming the flag; ``flag_values``: the env options those flags gave)."""
    from sonogym.envs import options

    with _bad_parameter():
        return options.parse_env_options(task, items, _FLAGGED_ENV_OPTIONS, flag_values)


def parse_patients(specs: list[str] | None) -> tuple[int | str, ...] | None:
    """``--patients`` / ``--patient`` values -> the env's ``patients``
    (``sonogym.envs.options.parse_patients``); None when none were given."""
    from sonogym.envs import options

    with _bad_parameter():
        return options.parse_patients(specs)


@app.command()
@with_options(RunOptions)
def sweep(
    task: Annotated[str, typer.Option(help="navigation, reconstruction or surgery.")],
    out: Annotated[Path, typer.Option(help="Sweep folder (sweep.md/csv, runs/, tune/, plots/).")],
    algo: Annotated[str, typer.Option(help=_rl_algorithms())] = "ppo",
    seeds: Annotated[
        int | None, typer.Option(help="Seeds per grid point (0, 1, ...; default 3).")
    ] = None,
    grid: Annotated[
        list[str] | None,
        typer.Option(
            help="key=v1,v2; repeatable. Keys: num_envs, net, obs_downsample, reward_scale, "
            "init_log_std, final_log_std, anneal_steps, <algorithm>.<field> (ppo.learning_rate), "
            "env.<option>."
        ),
    ] = None,
    samples: Annotated[
        int | None, typer.Option(help="Repetitions of the grid (Tune num_samples; default 1).")
    ] = None,
    address: Annotated[
        str | None, typer.Option(help="An existing Ray cluster (ray://host:10001); default local.")
    ] = None,
    max_concurrent: Annotated[
        int | None, typer.Option(help="Trials at once (default: as many as the CPUs hold).")
    ] = None,
    resume: Annotated[bool, typer.Option(help="Continue an interrupted sweep in --out.")] = False,
    force: Annotated[bool, typer.Option(help="Replace an existing sweep in --out.")] = False,
    options: RunOptions = ALL_DEFAULTS,
) -> None:
    """Several seeds and a hyperparameter grid on Ray Tune; every trial is a normal run folder
    (sonogym eval / plot / report work on it); a table of the trials and the mean ± 1 sigma
    learning curves at the end. Every trial takes the run options below."""
    from sonogym.agents.sweep import import_ray, parse_grid
    from sonogym.agents.sweep import sweep as run_sweep

    import_ray()  # says how to install Ray before anything else
    _check_positive(("--seeds", seeds), ("--samples", samples),
                    ("--max-concurrent", max_concurrent))  # fmt: skip
    with _bad_parameter():
        options.check()
    if resume:  # the sweep continues as sweep.json defines it: refuse what would change it
        given = {"--seeds": seeds, "--grid": grid, "--samples": samples}
        changed = [k for k, v in given.items() if v is not None] + options.given()
        if changed:
            raise typer.BadParameter(
                f"--resume continues the sweep as {out / 'sweep.json'} defines it; leave out "
                f"{', '.join(changed)} (or start a new sweep in another folder)"
            )
    with _bad_parameter():
        points = parse_grid(grid)
        kw = options.env_kwargs()
    run = {**options.train_kwargs(), "preset": options.preset or "auto",
           "device": options.device or "cpu", "env_kwargs": kw or None}  # fmt: skip
    res = run_sweep(task, algo, out, seeds=seeds or 3, grid=points, samples=samples or 1,
                    address=address, max_concurrent=max_concurrent, resume=resume, force=force,
                    log=typer.echo, **run)  # fmt: skip
    failed = [r for r in res.trials if r.status == "ERROR"]
    if failed and len(failed) == len(res.trials):  # nothing trained: not a success
        raise ValueError(
            f"all {len(failed)} trials failed (first, {failed[0].name}: {failed[0].error}); "
            f"see {res.out / 'sweep.md'}, fix the options and start again with --force"
        )
    from sonogym.evaluation.curves import plot_curves

    runs = sorted(p for p in (res.out / "runs").glob("*") if (p / "config.json").is_file())
    if runs:
        for p in plot_curves(runs, res.out / "plots", expert=False):
            typer.echo(f"wrote {p}")


def _pretrained_target(name: str, checkpoint: Path | None, out: Path | None):
    """(run folder, weights, output folder) of the shipped policy ``name`` for ``eval``."""
    from sonogym.evaluation import pretrained as shipped

    if checkpoint is not None:
        raise typer.BadParameter("--checkpoint is for --run; a pretrained policy has one")
    try:
        run, weights = shipped.pretrained_dir(name), shipped.weights(name)
    except ValueError as e:
        raise typer.BadParameter(str(e)) from None
    return run, weights, out or Path(f"runs/pretrained-{name}")


def _test_patients(protocol: str, patients: list[str] | None):
    """``eval``'s (env overrides, protocol): the protocol checked, or with ``--patients`` the
    test patients in place of the protocol's (then no protocol)."""
    from sonogym.evaluation.protocols import PROTOCOLS

    if protocol not in PROTOCOLS:
        raise typer.BadParameter(f"unknown protocol {protocol!r}; choose from {list(PROTOCOLS)}")
    if not patients:
        return None, protocol
    if protocol != "idt":
        raise typer.BadParameter(
            f"--patients replaces the test patients; it cannot be combined with --protocol "
            f"{protocol}, which sets its own"
        )
    return {"patients": parse_patients(patients)}, None


@app.command("eval")
def eval_(
    run: Annotated[
        Path | None,
        typer.Option(help="Run directory written by `sonogym train` or `sonogym il-train`."),
    ] = None,
    pretrained: Annotated[
        str | None,
        typer.Option(
            help="A policy that ships with sonogym instead of --run ('list' lists them); "
            "its files go to --out (default runs/pretrained-<name>)."
        ),
    ] = None,
    trials: Annotated[int, typer.Option(help="Episodes per controller.")] = 100,
    envs: Annotated[
        int | None, typer.Option(help="Parallel envs (default min(16, trials)).")
    ] = None,
    seed: Annotated[int, typer.Option(help="Seed of the evaluation starts.")] = 1000,
    device: Annotated[str, typer.Option(help="cpu or cuda[:i].")] = "cpu",
    protocol: Annotated[
        str,
        typer.Option(
            help="idt (the run's simulator and patients), odt-sim (learned net 4) or "
            "odt-patient (held-out patient 5)."
        ),
    ] = "idt",
    held_out: Annotated[
        int, typer.Option(help="odt-patient: number of held-out phantoms (seeds 5, 6, ...).")
    ] = 1,
    checkpoint: Annotated[
        Path | None,
        typer.Option(
            help="Checkpoint to evaluate: a file, or 'selected' (the one `sonogym select` "
            "chose); default the run's newest readable one."
        ),
    ] = None,
    filter_mode: Annotated[
        str | None,
        typer.Option(
            help="ppo-sf runs: safety filter mode, search (nearest action predicted safe) or "
            "zero (the paper's: no motion); default the run's."
        ),
    ] = None,
    filter_threshold: Annotated[
        float | None,
        typer.Option(help="ppo-sf runs: filter where Q_c > this, in [0, 1]; default the run's."),
    ] = None,
    patients: Annotated[
        list[str] | None,
        typer.Option(
            help="Test on these patients instead (phantom seeds, ranges A-B or subject "
            "folders; repeatable); not with --protocol other than idt."
        ),
    ] = None,
    name: Annotated[
        str | None,
        typer.Option(
            help="Name of the saved table and episode log (default: the protocol's; "
            "'custom' with --patients)."
        ),
    ] = None,
    out: Annotated[
        Path | None,
        typer.Option(
            help="Folder for the table, episode log and figure (default: the run folder; "
            "give one for a run you cannot write to)."
        ),
    ] = None,
    controllers: Annotated[
        list[str] | None,
        typer.Option(
            help="Evaluate only these (policy, expert, random; ppo-sf runs also "
            "unfiltered); repeatable. Default: all."
        ),
    ] = None,
) -> None:
    """Evaluate a run's policy (or a shipped one), the task's expert and a random policy; print
    and save the table, the per-episode log (episodes/<protocol>.npz) and a trajectory figure."""
    from sonogym.evaluation import pretrained as shipped
    from sonogym.evaluation.rl_eval import (
        CONTROLLERS,
        check_writable,
        evaluate_run,
        format_table,
        table_stem,
    )
    from sonogym.outputs import undo_on_failure

    if (run is None) == (pretrained is None):
        raise typer.BadParameter("give --run RUN or --pretrained NAME (one of them)")
    if pretrained == "list":
        typer.echo(shipped.listing())
        return
    if pretrained is not None:
        run, checkpoint, out = _pretrained_target(pretrained, checkpoint, out)
    overrides, protocol = _test_patients(protocol, patients)
    log = name or protocol or "custom"
    stem = table_stem(log)
    dest = Path(out or run)
    written = [dest / f"{stem}.json", dest / f"{stem}.md", dest / "episodes" / f"{log}.npz",
               dest / f"trajectories-{log}.png"]  # fmt: skip
    what = f"pretrained policy {pretrained}" if pretrained else f"run {run}"
    try:
        check_writable(dest, log)  # before saying where the results go
        typer.echo(f"eval: {what}, {trials} episodes per controller; results go to {dest}/",
                   err=True)  # fmt: skip
        with undo_on_failure(*written):
            results = evaluate_run(
                run, trials=trials, envs=envs, seed=seed, device=device, protocol=protocol,
                held_out_patients=held_out, checkpoint=checkpoint, env_overrides=overrides,
                name=name, out=out, controllers=tuple(controllers) if controllers else CONTROLLERS,
                safety_filter={"mode": filter_mode, "threshold": filter_threshold},
                progress=True,
            )  # fmt: skip
    except (FileNotFoundError, ValueError) as e:
        raise typer.BadParameter(str(e)) from None
    table = dest / f"{stem}.md"
    typer.echo(table.read_text() if table.is_file() else format_table(results), nl=False)
    typer.echo(
        f"wrote {out or run}/{stem}.md, {stem}.json, episodes/{log}.npz, trajectories-{log}.png"
    )


@app.command()
def select(
    run: Annotated[Path, typer.Option(help="Run folder written by `sonogym train`.")],
    patients: Annotated[
        list[str],
        typer.Option(
            help="Selection patients: phantom seeds, ranges A-B, subject folders or variants "
            "DIR@N; repeatable. Keep them apart from the patients your figures report on."
        ),
    ],
    metric: Annotated[
        str | None, typer.Option(help="Metric to select on (default: the task's first).")
    ] = None,
    trials: Annotated[int, typer.Option(help="Episodes per checkpoint.")] = 50,
    envs: Annotated[int | None, typer.Option(help="Parallel envs (default 16).")] = None,
    seed: Annotated[int, typer.Option(help="Seed of the selection episodes' starts.")] = 2000,
    checkpoint: Annotated[
        list[Path] | None,
        typer.Option(help="Only these checkpoints (repeatable; default: all of the run's)."),
    ] = None,
    device: Annotated[str, typer.Option(help="cpu or cuda[:i].")] = "cpu",
) -> None:
    """Choose a run's checkpoint on selection patients: each checkpoint's policy is evaluated
    there and the best mean of the metric wins (<run>/selection.json, selection.md; each
    evaluation in <run>/selection/). `sonogym export` then ships that checkpoint and refuses
    a model card that reports a figure on a selection patient."""
    from sonogym.evaluation.checkpoint_selection import select_checkpoint
    from sonogym.evaluation.selection import selection_markdown

    _check_positive(("--trials", trials), ("--envs", envs))
    try:
        summary = select_checkpoint(
            run, parse_patients(patients), metric=metric, trials=trials, envs=envs, seed=seed,
            checkpoints=checkpoint, device=device, log=lambda m: typer.echo(m, err=True),
        )  # fmt: skip
    except (FileNotFoundError, KeyError, ValueError) as e:
        raise typer.BadParameter(str(e).strip("'\"")) from None
    typer.echo(selection_markdown(summary), nl=False)
    typer.echo(f"wrote {run}/selection.json, selection.md, selection/")


@app.command(context_settings={"allow_extra_args": True})
def plot(
    ctx: typer.Context,
    runs: Annotated[
        list[Path],
        typer.Option(
            help="Run folders, or folders holding runs; repeatable, and further paths may follow "
            "(--runs runs/nav-*)."
        ),
    ],
    out: Annotated[Path, typer.Option(help="Folder for the PNG, CSV and curves.md.")] = Path(
        "runs/plots"
    ),
    metric: Annotated[
        list[str] | None,
        typer.Option(help="TensorBoard scalar; repeatable (default 'Episode / return')."),
    ] = None,
    expert: Annotated[
        bool, typer.Option(help="Draw the expert's mean as a reference line.")
    ] = True,
    expert_episodes: Annotated[
        int, typer.Option(help="Expert episodes when no eval log gives its mean.")
    ] = 4,
) -> None:
    """Learning curves over seeds (mean ± 1 sigma per task and algorithm) from TensorBoard logs."""
    from sonogym.evaluation.curves import DEFAULT_METRIC, discover_runs, plot_curves

    try:
        found = discover_runs([*runs, *map(Path, ctx.args)])
    except FileNotFoundError as e:
        raise typer.BadParameter(str(e)) from None
    pngs = plot_curves(
        found, out, tuple(metric or [DEFAULT_METRIC]), expert=expert,
        expert_episodes=expert_episodes,
    )  # fmt: skip
    for p in pngs:
        typer.echo(f"wrote {p}")
    typer.echo(f"wrote {out}/curves.md ({len(found)} run{'s' if len(found) != 1 else ''})")


@app.command(context_settings={"allow_extra_args": True})
def report(
    ctx: typer.Context,
    task: Annotated[str, typer.Option(help="navigation, reconstruction or surgery.")],
    runs: Annotated[
        list[Path],
        typer.Option(
            help="Run folders, or folders holding runs; repeatable, and further paths may follow."
        ),
    ],
    out: Annotated[
        Path | None, typer.Option(help="Report folder (default runs/report-<task>).")
    ] = None,
    curves: Annotated[bool, typer.Option(help="Include the learning curves.")] = True,
) -> None:
    """The paper's tables and figures for a task from finished, evaluated runs (Markdown, CSV,
    PNG in one folder)."""
    from sonogym.evaluation.report import build_report

    paths = [*runs, *map(Path, ctx.args)]
    out = out or Path(f"runs/report-{task}")
    cmd = f"sonogym report --task {task} --runs " + " ".join(map(str, paths))
    try:
        md = build_report(task, paths, out, curves=curves, command=cmd)
    except (FileNotFoundError, ValueError) as e:
        raise typer.BadParameter(str(e)) from None
    typer.echo(f"wrote {md} and its tables and figures in {out}/")


@app.command()
def export(
    run: Annotated[Path, typer.Option(help="Run folder written by `sonogym train`.")],
    name: Annotated[str, typer.Option(help="Name of the shipped policy (e.g. navigation).")],
    to: Annotated[
        Path | None,
        typer.Option(
            help="Folder of pretrained policies to write NAME/ into (required: the package's "
            "own folder is named only on purpose)."
        ),
    ] = None,
    checkpoint: Annotated[
        Path | None,
        typer.Option(
            help="Checkpoint (default: the one `sonogym select` chose, else the run's newest "
            "readable one)."
        ),
    ] = None,
    notes: Annotated[str, typer.Option(help="Text for the model card's notes.")] = "",
    force: Annotated[
        bool,
        typer.Option(
            help="Replace a policy of that name in --to: only the files export writes; other "
            "files there are kept."
        ),
    ] = False,
) -> None:
    """Make a run's policy a pretrained policy: its config, acting weights (safetensors) and a
    model card from its checkpoint times and the evaluations in its folder. An existing policy
    of that name is refused without --force; a run that stopped early or was never evaluated
    gets a warning, and its card says so."""
    from sonogym.evaluation.pretrained import PRETRAINED_DIR, export_pretrained

    if to is None:
        raise typer.BadParameter(
            f"give --to FOLDER, the folder of pretrained policies to write {name}/ into (the "
            f"policies that ship with sonogym are in {PRETRAINED_DIR}; name it to replace one)"
        )
    dest = export_pretrained(run, name, to, checkpoint, notes, force=force,
                             log=lambda m: typer.echo(m, err=True),
                             warn=lambda m: typer.echo(f"warning: {m}", err=True))  # fmt: skip
    typer.echo(f"wrote {dest}/ (config.json, policy.safetensors, model_card.json, model_card.md)")


@app.command()
def reproduce(
    name: Annotated[
        str,
        typer.Argument(
            help="The published result: table1, navigation, reconstruction, population, "
            "imitation, curves, table1-lb, navigation-lb, or all of them in that order."
        ),
    ],
    preset: Annotated[
        str, typer.Option(help="cpu (the recipe as published) or paper (the paper's settings).")
    ] = "cpu",
    dry_run: Annotated[
        bool, typer.Option(help="Print the commands and their CPU time; run nothing.")
    ] = False,
    root: Annotated[
        Path | None,
        typer.Option(
            help="Folder the recipe's outputs (runs/, docs/results/, reports/) go under, made "
            "if absent (default: the current folder)."
        ),
    ] = None,
) -> None:
    """Run the train / record / il-train / eval / report commands that make a published result
    (docs/results.md), in order, skipping those whose output is complete; run it again to
    resume. Every output goes under --root (said at the start); the data the recipes read ships
    with sonogym."""
    import subprocess

    from sonogym import reproduce as R
    from sonogym.reproduce_root import run_command, working_in

    with _bad_parameter():
        # an unknown result or preset, before any folder is touched
        R.recipe(next(iter(R.RECIPES)) if name == R.ALL else name, preset)
    with working_in(root or Path.cwd(), create=not dry_run) as where:
        lines = iter([f"; outputs under {where}/"])  # said on the plan's first line

        def log(line: str) -> None:
            typer.echo(line + next(lines, ""))

        try:
            R.reproduce(name, preset, dry_run, log=log, runner=run_command)
        except ValueError as e:
            raise typer.BadParameter(str(e)) from None
        except subprocess.CalledProcessError as e:
            typer.echo(f"stopped: `{e.cmd}` exited with {e.returncode}; fix it and run again")
            raise typer.Exit(e.returncode) from None


@app.command()
def view(
    task: Annotated[
        str | None, typer.Option(help="Step this task's env: navigation, reconstruction, surgery.")
    ] = None,
    policy: Annotated[
        str, typer.Option(help="Who acts: expert, random or a run folder (train / il-train).")
    ] = "expert",
    pretrained: Annotated[
        str | None, typer.Option(help="A policy that ships with sonogym acts instead.")
    ] = None,
    patient: Annotated[
        str | None,
        typer.Option(help="A TotalSegmentator subject folder (or DIR@N, a variant of it)."),
    ] = None,
    seed: Annotated[
        int | None, typer.Option(help="Phantom seed of the patient (default 0).")
    ] = None,
    episode_seed: Annotated[int, typer.Option(help="Seed of the env's reset (the starts).")] = 0,
    steps: Annotated[
        int | None, typer.Option(help="Env steps to show (default: one episode).")
    ] = None,
    phantom_spacing: Annotated[
        float | None, typer.Option(help="Voxel size of phantoms, mm (default: the env's 1).")
    ] = None,
    env_option: Annotated[
        list[str] | None,
        typer.Option(help="KEY=VALUE env option, e.g. episode_length=100; repeatable."),
    ] = None,
    run: Annotated[
        Path | None,
        typer.Option(help="Replay a run's saved evaluation episode (episodes/<protocol>.npz)."),
    ] = None,
    protocol: Annotated[str, typer.Option(help="--run: the episode log's name.")] = "idt",
    controller: Annotated[
        str | None,
        typer.Option(help="--run: policy, expert or random (default: the policy)."),
    ] = None,
    dataset: Annotated[
        Path | None, typer.Option(help="Replay an episode of a recorded LeRobot dataset.")
    ] = None,
    episode: Annotated[int, typer.Option(help="--run / --dataset: the episode to show.")] = 0,
    save: Annotated[
        Path | None,
        typer.Option(help="Write the view to this .rrd file (default runs/view/<name>.rrd)."),
    ] = None,
    web: Annotated[
        bool, typer.Option(help="Serve Rerun's web viewer on localhost instead (Ctrl-C stops).")
    ] = False,
    port: Annotated[
        int, typer.Option(help="--web: the viewer's port (its data stream uses the next one).")
    ] = 9090,
    force: Annotated[
        bool,
        typer.Option(help="--save: replace an existing file that is not a sonogym recording."),
    ] = False,
) -> None:
    """A 3-D view of an env stepped by a policy, a run's saved episode or a dataset's episode
    in Rerun: the patient's skin and bones, the arms, the probe with its live image, the goal,
    the drill and its planned corridor, reconstructed bone, images and rewards over time.
    Needs the viewer extra: pip install 'sonogym[viewer]'."""
    from sonogym.viewer import require_rerun

    try:
        require_rerun()
    except ImportError as e:
        typer.echo(f"sonogym: error: {e}", err=True)
        raise SystemExit(1) from None
    from sonogym.viewer.command import ViewRequest, run_view

    replay = run is not None or dataset is not None
    env_flags = {"--task": task, "--pretrained": pretrained, "--patient": patient,
                 "--seed": seed, "--steps": steps, "--phantom-spacing": phantom_spacing,
                 "--env-option": env_option,
                 "--policy": None if policy == "expert" else policy}  # fmt: skip
    given = [k for k, v in env_flags.items() if v is not None]
    if replay and given:
        raise typer.BadParameter(f"{', '.join(given)} step an env; --run / --dataset replay "
                                 "what was saved: leave them out")  # fmt: skip
    if patient is not None and seed is not None:
        raise typer.BadParameter("give --patient or --seed, not both")
    _check_positive(("--steps", steps))
    options: dict[str, Any] = {}
    if not replay:
        if task is None and pretrained is None and policy in ("expert", "random"):
            raise typer.BadParameter("give --task, --policy RUN or --pretrained NAME")
        if task is not None:
            options = parse_env_options(task, env_option)
        elif env_option:
            raise typer.BadParameter("--env-option needs --task (the options are the task's)")
        if patient is not None or seed is not None:
            options["patients"] = (seed,) if seed is not None else parse_patients([patient])
        if phantom_spacing is not None:
            options["phantom_spacing"] = phantom_spacing * 1e-3
    req = ViewRequest(task=task, policy=policy, pretrained=pretrained, env_options=options,
                      steps=steps, seed=episode_seed, run=run, protocol=protocol,
                      controller=controller, dataset=dataset, episode=episode)  # fmt: skip
    try:
        run_view(req, save=save, web=web, web_port=port, log=typer.echo, force=force,
                 progress=True)  # fmt: skip
    except (FileNotFoundError, IndexError, ValueError) as e:
        raise typer.BadParameter(str(e)) from None


@app.command("lb-data")
def lb_data(
    out: Annotated[Path, typer.Option(help="Folder for manifest.json + pairs/.")],
    pairs: Annotated[int, typer.Option(help="Number of CT/US pairs.")] = 2000,
    seed: Annotated[
        int, typer.Option(help="First phantom seed (keep apart from env seeds: >= 1000).")
    ] = 1000,
    phantoms: Annotated[int, typer.Option(help="Phantoms (seeds seed, seed+1, ...).")] = 5,
    size: Annotated[
        list[int] | None, typer.Option(help="Image size: H [W] in pixels (default 192 160).")
    ] = None,
    pixel_mm: Annotated[float, typer.Option(help="Pixel spacing, mm.")] = 0.5,
    phantom_mm: Annotated[float, typer.Option(help="Phantom voxel size, mm (0.5-2).")] = 1.0,
    test_fraction: Annotated[float, typer.Option(help="Held-out fraction per phantom.")] = 0.125,
) -> None:
    """Write default learned-simulator training pairs (CT slice + `physical` model image)."""
    from sonogym.learned_training.data import write_default_pairs

    hw = list(size or [192, 160])
    if len(hw) == 1:
        hw = hw * 2
    if len(hw) != 2:
        raise typer.BadParameter("--size takes one or two integers")
    path = write_default_pairs(
        out, n=pairs, seeds=range(seed, seed + phantoms), image_size=(hw[0], hw[1]),
        pixel_spacing=pixel_mm * 1e-3, phantom_spacing=phantom_mm * 1e-3,
        test_fraction=test_fraction, rng_seed=seed, progress=True,
    )  # fmt: skip
    typer.echo(f"wrote {pairs} pairs and {path}")


@app.command("lb-train")
def lb_train(
    data: Annotated[Path, typer.Option(help="Paired-data folder (manifest.json + pairs).")],
    out: Annotated[Path, typer.Option(help="Run folder (generator.pt, metrics.json, tb/).")],
    seed: Annotated[int, typer.Option(help="Training seed (one net per seed).")] = 0,
    steps: Annotated[int, typer.Option(help="Optimiser steps.")] = 2000,
    width: Annotated[int, typer.Option(help="U-Net base width (paper: 64).")] = 16,
    depth: Annotated[int, typer.Option(help="U-Net down-sampling steps (paper: 6).")] = 4,
    batch_size: Annotated[int, typer.Option(help="Pairs per step.")] = 8,
    disc_width: Annotated[int, typer.Option(help="PatchGAN base width (pix2pix: 64).")] = 32,
    device: Annotated[str, typer.Option(help="cpu or cuda[:i].")] = "cpu",
    progress: Annotated[bool, typer.Option(help="Show a progress bar.")] = True,
) -> None:
    """Train one pix2pix CT -> ultrasound generator on paired data."""
    from sonogym.learned_training.data import PairedDataError
    from sonogym.learned_training.train import train_pix2pix

    try:
        m = train_pix2pix(
            data, out, seed=seed, steps=steps, width=width, depth=depth,
            batch_size=batch_size, disc_width=disc_width, device=device, progress=progress,
        )  # fmt: skip
    except PairedDataError as e:
        raise typer.BadParameter(str(e)) from None
    t = m["test"]
    if t["n"]:
        typer.echo(
            f"held-out ({t['n']} pairs): SSIM {t['ssim']:.4f}  PSNR {t['psnr']:.2f} dB  "
            f"L1 {t['l1']:.4f}  (LPIPS not available offline)"
        )
    else:
        typer.echo("no held-out pairs: SSIM / PSNR not computed")
    typer.echo(f"wrote {out}/generator.pt, metrics.json, losses.jsonl, tb/")


def main() -> None:
    """The ``sonogym`` entry point: bad input (a missing or malformed file, an invalid option,
    a folder that already holds a run, an output that cannot be written) ends with one line on
    stderr naming the problem and the fix, not a traceback; Ctrl-C ends with one line saying
    what was kept (an interrupted training run has saved a checkpoint) and exits with 130."""
    click = _click_exceptions()

    from sonogym.outputs import CommandInterrupted
    from sonogym.runs import TrainingInterrupted

    try:
        code = app(standalone_mode=False)
    except TrainingInterrupted:  # its message is out already
        raise SystemExit(130) from None
    except CommandInterrupted as e:
        _error(f"interrupted: {e}", 130)
    except click.NoArgsIsHelpError as e:
        e.show()
        raise SystemExit(e.exit_code) from None
    except click.ClickException as e:  # typer's usage errors, in one line
        _error(_usage_message(e), e.exit_code)
    except typer.Abort:
        _error("aborted", 1)
    except (ValueError, OSError) as e:  # includes the loaders' named errors
        _error(f"error: {e}", 1)
    if code == 130:  # Ctrl-C outside the commands' own handling
        _error("interrupted", 130)
    if isinstance(code, int) and code:
        raise SystemExit(code)


def _click_exceptions() -> Any:
    """The exceptions of the click typer runs on (typer >= 0.20 carries its own copy)."""
    try:
        from typer._click import exceptions
    except ImportError:
        from click import exceptions
    return exceptions


def _error(line: str, code: int) -> typing.NoReturn:
    typer.echo(f"sonogym: {' '.join(line.split())}", err=True)
    raise SystemExit(code)


def _usage_message(e: Any) -> str:
    """A usage error's message as one line: ``error: <what>``, with where to read the options
    for an unknown or missing option."""
    click = _click_exceptions()
    msg = e.format_message()
    if isinstance(e, click.BadParameter) and e.param is None and e.param_hint is None:
        return f"error: {msg.removeprefix('Invalid value: ')}"
    ctx = getattr(e, "ctx", None)
    if ctx is None or (
        isinstance(e, click.BadParameter) and not isinstance(e, click.MissingParameter)
    ):
        return f"error: {msg}"
    command = " ".join(["sonogym"] + ([ctx.info_name] if ctx.parent is not None else []))
    return f"error: {msg} (see {command} --help)"


if __name__ == "__main__":
    main()
