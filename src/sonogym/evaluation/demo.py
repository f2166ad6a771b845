"""``sonogym demo``: run every registered task's expert (or heuristic) for one episode and write
what it saw.

Outputs in the run folder: ``<task>_frames.png`` (a sheet of ultrasound frames along the way),
``<task>.mp4`` (env 0: the ultrasound image beside a top-down view of the back with the probe's
path and the target), and ``metrics.md`` / ``metrics.json`` (the task's metrics, mean and std
over the demo's envs).
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from sonogym.envs.policy import ExpertPolicy
from sonogym.envs.registry import get_task, make_vec, task_names
from sonogym.envs.rollout import rollout
from sonogym.evaluation.trained import load_run, run_policy
from sonogym.runs import atomic_write_text
from sonogym.tasks.demo import task_demo


def run_demo(
    out: str | Path = "runs/demo",
    num_envs: int = 4,
    seed: int = 0,
    tasks: tuple[str, ...] | None = None,
    log: Callable[[str], None] = print,
    patients: tuple | None = None,
) -> dict:
    """Run the demo and return the metrics table (also written to ``out``). ``patients``:
    phantom seeds and/or TotalSegmentator subject folders (default: the tasks' phantom 0).
    Where a trained policy of a task ships with sonogym (``sonogym eval --pretrained list``),
    it runs beside the expert on its model card's test patients (``patients`` if given), at
    least ``POLICY_EPISODES`` episodes, and its card's figures are printed beside its own."""
    from sonogym.evaluation import pretrained as shipped

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    results = {}
    over = {"patients": patients} if patients else {}
    for name in tasks or task_names():
        task = get_task(name)
        env = make_vec(name, num_envs, **over)
        runs = [(name, task.expert_label, env, ExpertPolicy(env, task.expert))]
        cards = {}
        for policy_name in shipped.available():
            run = load_run(shipped.pretrained_dir(policy_name))
            if run.task != name:
                continue
            # a fair sample: the model card's first test patients (never the policy's training
            # cohort), POLICY_EPISODES starts, images as evaluated; --patients overrides them
            card = card_figures(shipped.read_card(policy_name))
            test = patients or (card["patients"] if card else env.cfg.patients)
            n = max(num_envs, POLICY_EPISODES)
            penv = make_vec(name, n, **run.evaluation_env_kwargs({"patients": tuple(test)}))
            policy = run_policy(run, penv, shipped.weights(policy_name))
            key = f"{name}_pretrained-{policy_name}"
            runs.append((key, f"pretrained {policy_name}", penv, policy))
            cards[key] = card
        for key, label, e, policy in runs:
            t0 = time.perf_counter()
            final, sheet, frames = _episode(e, policy, seed, name)
            metrics = {k: _mean_std(final[k]) for k in (*task.metric_keys, "return")}
            results[key] = {"controller": label, "envs": e.num_envs,
                            "patients": [str(p) for p in e.cfg.patients],
                            "seconds": time.perf_counter() - t0, "metrics": metrics}  # fmt: skip
            _write_sheet(out / f"{key}_frames.png", sheet, f"{name} ({label})")
            _write_video(out / f"{key}.mp4", frames)
            log(f"{name} ({label}, {e.num_envs} episodes): {_figures(metrics)}")
            card = cards.get(key)
            if card:
                results[key]["model_card"] = card
                where = f"{card['evaluation']}, {card['trials']} episodes"
                log(f"  its model card ({where}): {_figures(card['metrics'])}")
    atomic_write_text(out / "metrics.json", json.dumps(results, indent=1))
    atomic_write_text(out / "metrics.md", _markdown(results))
    log(f"wrote {out}/metrics.md, metrics.json, *_frames.png, *.mp4")
    return results


#: Episodes a shipped policy runs in the demo (at least): enough starts that its mean is a
#: fair sample of what its model card reports, still a few seconds of the demo.
POLICY_EPISODES = 16


def card_figures(card: dict) -> dict | None:
    """The figures the demo shows beside a shipped policy's: its model card's first
    evaluation on named test patients (name, patients, trials, policy's mean and std per
    metric); None when the card has none."""
    for name, e in (card.get("evaluations") or {}).items():
        patients = (e.get("test_env") or {}).get("patients")
        if patients:
            pol = e["results"].get("policy", {})
            return {"evaluation": name, "patients": list(patients), "trials": e.get("trials"),
                    "metrics": {k: tuple(v) for k, v in pol.items() if k != "return"}}  # fmt: skip
    return None


def _episode(env, policy, seed: int, name: str):
    """One episode of every env: (final metrics, frame sheet, video frames of env 0)."""
    demo = task_demo(name)
    frames, paths, sheet = [], [], []
    final = None
    for step in rollout(env, policy, env.episode_length, seed=seed):
        if step.final_info is not None:
            final = step.final_info
            img = demo.image(step.final_obs)
        else:
            img = demo.image(step.next_obs)
        paths.append(demo.point(env, step.next_info) if final is None else paths[-1])
        frames.append(demo.frame(env, img, np.array(paths)))
        t = step.t
        if t % max(1, env.episode_length // 8) == 0 or final is not None:
            sheet.append((t + 1, img.cpu().numpy()))
    if final is None:
        raise RuntimeError(f"{name}: the episode did not end within {env.episode_length} steps")
    return final, sheet, frames


def _write_video(path: Path, frames: list[np.ndarray], fps: int = 30) -> None:
    import imageio.v2 as imageio

    with imageio.get_writer(path, fps=fps, codec="libx264", quality=7) as w:
        for f in frames:
            w.append_data(f)


def _figures(metrics: dict) -> str:
    return ", ".join(f"{k} {m:.2f} ± {s:.2f}" for k, (m, s) in metrics.items())


def _mean_std(values) -> tuple[float, float]:
    """Mean and sample std over envs of a (N,) tensor (std 0 for one env, not NaN)."""
    v = values.float()
    return float(v.mean()), float(v.std()) if len(v) > 1 else 0.0


def _write_sheet(path: Path, sheet: list[tuple[int, np.ndarray]], name: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(sheet)
    cols = min(n, 5)
    rows = math.ceil(n / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(3 * cols, 3.6 * rows), squeeze=False)
    for ax in axes.flat:
        ax.axis("off")
    for ax, (t, img) in zip(axes.flat, sheet, strict=False):
        ax.imshow(img, cmap="gray", vmin=0, vmax=1, aspect="equal")
        ax.set_title(f"step {t}")  # the controller once, above: long names ran into each other
    fig.suptitle(name)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def _markdown(results: dict) -> str:
    lines = ["| task | controller | metric | mean | std |", "|---|---|---|---|---|"]
    for key, r in results.items():
        task = key.split("_pretrained-")[0]
        for k, (m, s) in r["metrics"].items():
            lines.append(f"| {task} | {r['controller']} | {k} | {m:.3f} | {s:.3f} |")
        card = r.get("model_card")
        for k, (m, s) in (card["metrics"] if card else {}).items():
            who = f"{r['controller']}: model card ({card['evaluation']}, {card['trials']} episodes)"
            lines.append(f"| {task} | {who} | {k} | {m:.3f} | {s:.3f} |")
    return "\n".join(lines) + "\n"
