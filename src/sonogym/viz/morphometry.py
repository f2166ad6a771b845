"""Phantoms against a real subject: the population table, the comparison table and the
side-by-side figure that ``sonogym morphometry`` writes (docs/anatomy.md shows them).

The measurements are ``sonogym.anatomy.morphometry``'s. The population is phantoms of seeds
``seeds`` built at ``spacing``; the real subject is loaded at ``subject_spacing`` (1 mm
reproduces a 3 mm TotalSegmentator mask voxel for voxel). ``population.json`` keeps every row
with the generator version, so that a test can rebuild a few seeds and check the table is the
generator's, and can check the real subject against it without building 40 phantoms.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from sonogym.anatomy import labels as L
from sonogym.anatomy import morphometry as M

#: Percentiles of the population that bound "inside".
PERCENTILES = (5.0, 95.0)
#: Marks around the table that ``update_doc`` replaces in a markdown file.
DOC_BEGIN = "<!-- morphometry table: begin (sonogym morphometry writes it) -->"
DOC_END = "<!-- morphometry table: end -->"
_NAMES = {
    "tip_depth": "skin to spinous tip",
    "lamina_depth": "skin to lamina",
    "interlaminar_window": "interlaminar window",
    "tp_span": "transverse-process span",
    "facet_width": "facet joints, left to right",
    "body_width": "body width",
    "body_depth": "body depth",
}


def measure_population(
    seeds: Sequence[int], spacing: float, log: Callable[[str], None] | None = None
) -> dict[int, dict[str, float]]:
    """Build and measure the phantom of every seed (``spacing`` in metres)."""
    from sonogym.anatomy import PhantomParams, make_phantom

    rows = {}
    for i, seed in enumerate(seeds):
        rows[int(seed)] = M.measure(make_phantom(int(seed), PhantomParams(spacing=spacing))).flat()
        if log:
            log(f"phantom {seed} measured ({i + 1}/{len(seeds)})")
    return rows


def population_bounds(rows: dict) -> dict[str, tuple[float, float, float]]:
    """Per value: (5th percentile, median, 95th percentile) over the rows."""
    keys = next(iter(rows.values())).keys()
    out = {}
    for k in keys:
        v = np.array([r[k] for r in rows.values()], dtype=np.float64)
        lo, med, hi = np.nanpercentile(v, [PERCENTILES[0], 50.0, PERCENTILES[1]])
        out[k] = (float(lo), float(med), float(hi))
    return out


def outside(real: dict[str, float], bounds: dict) -> list[str]:
    """Keys whose real value is missing, NaN or outside the population's 5-95 % range."""
    bad = []
    for k, (lo, _, hi) in bounds.items():
        v = real.get(k, math.nan)
        if not (math.isfinite(v) and lo <= v <= hi):
            bad.append(k)
    return bad


def table_markdown(real: dict[str, float], bounds: dict, n: int) -> str:
    """The comparison table (markdown): real value, phantom median and 5-95 % range."""
    lines = [
        f"Real subject against {n} phantoms (mm; population median and 5-95 % range).",
        "",
        "| level | measure | real | phantoms | 5-95 % | inside |",
        "|---|---|---|---|---|---|",
    ]

    def row(first: str, second: str, k: str) -> str:
        lo, med, hi = bounds[k]
        ok = "yes" if k not in outside(real, {k: bounds[k]}) else "**no**"
        return f"| {first} | {second} | {real[k]:.1f} | {med:.1f} | {lo:.1f}-{hi:.1f} | {ok} |"

    for lv in M.LEVELS:
        for m in M.LEVEL_MEASURES:
            lines.append(row(lv, _NAMES[m], f"{lv} {m}"))
    lines += [
        "",
        "First-bone-hit depth (mm) at the L4 goal views, across the probe's width (lateral "
        f"offset u in mm; {M.PROFILE_DEPTH:.0f} = no bone in the image).",
        "",
        "| view | u | real | phantoms | 5-95 % | inside |",
        "|---|---|---|---|---|---|",
    ]
    for view in M.GOAL_VIEWS:
        for u in M.PROFILE_OFFSETS:
            lines.append(row(view, f"{u:+.0f}", f"{view} {u:+.0f}"))
    lines += [
        "",
        "Skin to paraspinal muscle (mm) at the transverse L4 goal view, across the probe's width "
        f"(the first muscle sample before any bone; {M.PROFILE_DEPTH:.0f} = bone or nothing "
        "first).",
        "",
        "| view | u | real | phantoms | 5-95 % | inside |",
        "|---|---|---|---|---|---|",
    ]
    for u in M.PROFILE_OFFSETS:
        lines.append(row("transverse", f"{u:+.0f}", f"{M.MUSCLE_VIEW} {u:+.0f}"))
    return "\n".join(lines) + "\n"


def representative_seed(rows: dict, bounds: dict) -> int:
    """The seed whose per-level values lie closest to the population medians (scaled by each
    value's 5-95 % range): the phantom the figure shows."""
    keys = [f"{lv} {m}" for lv in M.LEVELS for m in M.LEVEL_MEASURES]

    def cost(r):
        return sum(((r[k] - bounds[k][1]) / max(bounds[k][2] - bounds[k][0], 1e-6)) ** 2
                   for k in keys if math.isfinite(r[k]))  # fmt: skip

    return min(rows, key=lambda s: cost(rows[s]))


#: Display colours (RGB) of tissue classes in the label panels; anything else is "other".
_CLASSES = (
    ("air", (0.0, 0.0, 0.0), (0,)),
    ("skin", (0.85, 0.65, 0.5), (L.SKIN,)),
    ("fat", (0.95, 0.85, 0.35), (L.SUBCUTANEOUS_FAT,)),
    ("paraspinal muscle", (0.7, 0.25, 0.2), (86, 87)),
    ("psoas", (0.5, 0.15, 0.15), (88, 89)),
    ("ligament, fascia", (0.2, 0.8, 0.9), (L.SPINAL_LIGAMENTS, L.THORACOLUMBAR_FASCIA)),
    ("bone", (1.0, 1.0, 1.0), tuple(sorted(L.BONE_IDS))),
    ("disc", (0.3, 0.4, 0.9), (L.INTERVERTEBRAL_DISCS,)),
    ("canal, cord", (0.6, 0.3, 0.8), (L.SPINAL_CANAL, 79)),
)
_OTHER = (0.55, 0.6, 0.55)


def label_rgb(labels: np.ndarray) -> np.ndarray:
    """(..., 3) display colours of a label image, by tissue class (``_CLASSES``)."""
    lut = np.tile(np.array(_OTHER), (256, 1))
    for _, colour, ids in _CLASSES:
        lut[list(ids)] = colour
    return lut[labels.astype(np.int64)]


def save_figure(phantom, real, values: tuple[dict, dict], bounds: dict, path: Path) -> Path:
    """Label slice and ultrasound (``physical`` model) of the transverse and sagittal L4 goal
    views, phantom beside the real subject, and their bone-hit profiles (``values``: the
    phantom's and the real subject's flat measurements) against the population's 5-95 % band."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch

    from sonogym.viz.render import render

    views = list(M.GOAL_VIEWS.items())
    shots = []
    for patient in (phantom, real):
        f = patient.landmarks.vertebra("L4")
        poses = [(float(f.centre[0]), float(f.centre[2]), yaw, 0.0) for _, yaw in views]
        shots.append(render(patient, poses, ("physical",)))
    fig = plt.figure(figsize=(15, 14))
    grid = fig.add_gridspec(3, 4, height_ratios=[1, 1, 0.75])
    for c, (who, r) in enumerate(zip((phantom.name, real.name), shots, strict=True)):
        s = r.slices
        h, w = s.ct.shape[2:]
        ext = (-w * s.probe.width_spacing * 500, w * s.probe.width_spacing * 500,
               h * s.probe.depth_spacing * 1e3, 0)  # fmt: skip
        for row, (view, _) in enumerate(views):
            ax = fig.add_subplot(grid[row, 2 * c])
            ax.imshow(label_rgb(s.labels[row, 0].numpy()), extent=ext, interpolation="nearest")
            ax.set_title(f"{who}: {view}, labels", fontsize=9)
            ax.set_ylabel("depth (mm)", fontsize=8)
            ax2 = fig.add_subplot(grid[row, 2 * c + 1])
            ax2.imshow(r.images["physical"][row, 0].numpy(), extent=ext, cmap="gray", vmin=0,
                       vmax=1)  # fmt: skip
            ax2.set_title(f"{who}: {view}, US (physical)", fontsize=9)
            for a in (ax, ax2):
                a.set_xlabel("lateral u (mm)", fontsize=8)
                a.tick_params(labelsize=7)
    u = np.array(M.PROFILE_OFFSETS)
    for c, (view, _) in enumerate(views):
        ax = fig.add_subplot(grid[2, 2 * c : 2 * c + 2])
        lo = [bounds[f"{view} {x:+.0f}"][0] for x in u]
        hi = [bounds[f"{view} {x:+.0f}"][2] for x in u]
        ax.fill_between(u, lo, hi, color="0.85", label="phantoms 5-95 %")
        for vals, style, name in zip(values, ("b.-", "r.-"), (phantom.name, real.name),
                                     strict=True):  # fmt: skip
            ax.plot(u, [vals[f"{view} {x:+.0f}"] for x in u], style, label=name)
        ax.set_ylim(M.PROFILE_DEPTH + 5, 0)
        ax.set_title(f"first bone hit across the {view} L4 goal view", fontsize=9)
        ax.set_xlabel("lateral u (mm)", fontsize=8)
        ax.set_ylabel("depth (mm)", fontsize=8)
        ax.legend(fontsize=7, loc="lower left")
    handles = [Patch(color=col, label=name) for name, col, _ in _CLASSES[1:]]
    handles.append(Patch(color=_OTHER, label="other soft tissue"))
    fig.legend(handles=handles, loc="upper center", ncol=len(handles), fontsize=8)
    fig.tight_layout(rect=(0, 0, 1, 0.97))
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=80)
    plt.close(fig)
    return path


def check_doc(doc: Path) -> str:
    """The text of ``doc``, a markdown file that holds both morphometry marks (``DOC_BEGIN``,
    ``DOC_END``, in that order) and can be rewritten; ``ValueError`` naming what is wrong."""
    import os

    if not doc.is_file():
        raise FileNotFoundError(f"--doc {doc} does not exist or is not a file")
    try:
        text = doc.read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise ValueError(f"--doc {doc} cannot be read as text ({e})") from None
    begin, end = text.find(DOC_BEGIN), text.find(DOC_END)
    if begin < 0 or end < begin:
        raise ValueError(
            f"--doc {doc} has no morphometry marks; add the lines {DOC_BEGIN!r} and {DOC_END!r} "
            "where the table belongs"
        )
    if not os.access(doc, os.W_OK):
        raise ValueError(f"--doc {doc} cannot be written; give a file you can write to")
    return text


def check_report(
    subject: str | Path, seeds: Sequence[int], spacing: float, subject_spacing: float,
    doc: str | Path | None = None,
) -> None:  # fmt: skip
    """Refuse, before anything is measured, what ``write_report`` would refuse late: no
    phantom seeds, a phantom or subject voxel size out of range (metres), a subject that is
    no folder, a ``doc`` without the marks."""
    from sonogym.anatomy import PhantomParams
    from sonogym.anatomy.totalseg import SPACING_RANGE

    if len(seeds) < 1:
        raise ValueError("the population needs at least one phantom seed")
    try:
        PhantomParams(spacing=spacing)
    except ValueError as e:
        raise ValueError(f"--spacing {spacing * 1e3:g} mm: {e}") from None
    lo, hi = SPACING_RANGE
    if not lo <= subject_spacing <= hi:
        raise ValueError(
            f"--subject-spacing {subject_spacing * 1e3:g} mm is outside {lo * 1e3:g}-"
            f"{hi * 1e3:g} mm"
        )
    if not Path(subject).is_dir():
        raise FileNotFoundError(f"--subject {subject} does not exist or is not a folder")
    if doc is not None:
        check_doc(Path(doc))


def update_doc(doc: Path, table: str, note: str) -> None:
    """Replace the text between ``DOC_BEGIN`` and ``DOC_END`` in ``doc`` with note + table."""
    text = check_doc(doc)
    head, rest = text.split(DOC_BEGIN, 1)
    _, tail = rest.split(DOC_END, 1)
    doc.write_text(f"{head}{DOC_BEGIN}\n{note}\n\n{table}{DOC_END}{tail}")


def write_report(
    out: str | Path,
    subject: str | Path,
    seeds: Sequence[int] = range(40),
    spacing: float = 0.002,
    subject_spacing: float = 0.001,
    figure_spacing: float = 0.001,
    doc: str | Path | None = None,
    command: str = "",
    log: Callable[[str], None] = print,
) -> dict[str, Path]:
    """What ``sonogym morphometry`` does: measure the real subject and the phantom population,
    write ``population.json``, ``morphometry.md`` and ``comparison.png`` to ``out`` (and the
    table into ``doc`` between its marks). Returns the written paths. The options are checked
    (``check_report``) before anything is measured; ``out`` is made when the results are
    written."""
    from sonogym.anatomy import PhantomParams, load_phantom, load_totalsegmentator
    from sonogym.anatomy.phantom import GENERATOR_VERSION

    out = Path(out)
    check_report(subject, seeds, spacing, subject_spacing, doc)
    log(f"measuring the real subject {Path(subject).name} at {subject_spacing * 1e3:g} mm")
    real = load_totalsegmentator(subject, spacing=subject_spacing, target="L4")
    m_real = M.measure(real)
    log(f"measured {real.name}; building and measuring {len(seeds)} phantoms")
    rows = measure_population(list(seeds), spacing, log)
    bounds = population_bounds(rows)
    pop = {
        "generator_version": GENERATOR_VERSION,
        "spacing_m": spacing,
        "subject": Path(subject).name,
        "subject_spacing_m": subject_spacing,
        "percentiles": list(PERCENTILES),
        "subject_values": m_real.flat(),
        "rows": {str(k): v for k, v in rows.items()},
    }
    paths = {"population": out / "population.json"}
    out.mkdir(parents=True, exist_ok=True)
    paths["population"].write_text(json.dumps(pop, indent=1) + "\n")
    table = table_markdown(m_real.flat(), bounds, len(rows))
    bad = outside(m_real.flat(), bounds)
    seed = representative_seed(rows, bounds)
    note = (
        f"Regenerate with `{command or 'sonogym morphometry'}`: {len(rows)} phantoms (seeds "
        f"{min(rows)}-{max(rows)}, generator version {GENERATOR_VERSION}) built at "
        f"{spacing * 1e3:g} mm, the real subject `{Path(subject).name}` loaded at "
        f"{subject_spacing * 1e3:g} mm. {len(bounds) - len(bad)} of {len(bounds)} real values "
        f"lie inside the phantoms' 5-95 % range"
        + (f"; outside: {', '.join(bad)}." if bad else ".")
        + f" The figure shows phantom {seed}, the seed closest to the population medians."
    )
    paths["table"] = out / "morphometry.md"
    paths["table"].write_text(f"# Phantoms against a real subject\n\n{note}\n\n{table}")
    phantom = load_phantom(seed, PhantomParams(spacing=figure_spacing))
    real_fig = real if subject_spacing == figure_spacing else load_totalsegmentator(
        subject, spacing=figure_spacing, target="L4")  # fmt: skip
    paths["figure"] = save_figure(phantom, real_fig, (rows[seed], m_real.flat()), bounds,
                                  out / "comparison.png")  # fmt: skip
    if doc is not None:
        update_doc(Path(doc), table, note)
        paths["doc"] = Path(doc)
    return paths
