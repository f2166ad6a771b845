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
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch


def _first_image(obs) -> torch.Tensor:
    """Env 0's 2-D image of an image observation (N, 1, H, W)."""
    return obs[0, 0]


def _probe_position(env, info) -> np.ndarray:
    return env.scene.probe_pos[0].cpu().numpy().copy()


@dataclass(frozen=True)
class DemoTask:
    """How to demo one task: its env id, its expert, its metrics, and how to draw env 0.

    ``image(obs)`` picks env 0's 2-D image for the frame sheet; ``track(env, info)`` the point
    whose path the video draws; ``frame(env, image, path)`` one RGB video frame."""

    env_id: str
    expert: Callable[[object, dict], torch.Tensor]
    metrics: tuple[str, ...]
    image: Callable[[object], torch.Tensor] = _first_image
    track: Callable[[object, dict], np.ndarray] = _probe_position
    frame: Callable[[object, torch.Tensor, np.ndarray], np.ndarray] | None = None


def _navigation_expert(env, info):
    from sonogym.envs.navigation import navigation_expert

    return navigation_expert(info["state"], action_scale=env.cfg.action_scale)


def _surgery_expert(env, info):
    from sonogym.envs.surgery import surgery_expert

    return surgery_expert(
        info["state"],
        info["radius"],
        skin_distance=env.cfg.skin_distance,
        action_scale=env.cfg.action_scale,
    )


def _surgery_image(obs) -> torch.Tensor:
    """Env 0's volume, its elevation slices side by side."""
    from sonogym.envs.surgery import volume_strip

    return volume_strip(obs["image"][0])


def _drill_tip_in_goal(env, info) -> np.ndarray:
    return info["state"][0, :3].cpu().numpy().copy()


def _surgery_frame(env, image: torch.Tensor, path: np.ndarray) -> np.ndarray:
    from sonogym.envs.surgery import surgery_frame

    frame = surgery_frame(env, path, image, zoom=4)
    return np.pad(frame, ((0, (-frame.shape[0]) % 16), (0, (-frame.shape[1]) % 16), (0, 0)))


def _reconstruction_heuristic(env, info):
    from sonogym.envs.reconstruction import heuristic_raster

    return heuristic_raster(env, info)


def _reconstruction_image(obs) -> torch.Tensor:
    """The reconstruction in the probe frame, projected over elevation: (depth, lateral),
    upsampled x5 to 200 x 200 (bone surface near the image plane shows as bright points)."""
    v = obs["reconstruction"][0].amax(1).T  # (z_U depth, x_U lateral)
    return v.repeat_interleave(5, 0).repeat_interleave(5, 1)


DEMO_TASKS: dict[str, DemoTask] = {
    "navigation": DemoTask(
        "SonoGym/Navigation-v0", _navigation_expert, ("position_error_mm", "angle_error_deg")
    ),
    "reconstruction": DemoTask(
        "SonoGym/Reconstruction-v0",
        _reconstruction_heuristic,
        ("coverage", "total_rotation_deg", "trajectory_length_mm"),
        image=_reconstruction_image,
    ),
    "surgery": DemoTask(
        "SonoGym/Surgery-v0",
        _surgery_expert,
        ("insertion_error_mm", "side_error_mm", "rotation_error_deg", "safe_ratio"),
        image=_surgery_image,
        track=_drill_tip_in_goal,
        frame=_surgery_frame,
    ),
}


def run_demo(
    out: str | Path = "runs/demo",
    num_envs: int = 4,
    seed: int = 0,
    tasks: tuple[str, ...] | None = None,
    log: Callable[[str], None] = print,
) -> dict:
    """Run the demo and return the metrics table (also written to ``out``)."""
    import gymnasium as gym

    import sonogym  # noqa: F401  (registers the envs)

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    results = {}
    for name in tasks or tuple(DEMO_TASKS):
        task = DEMO_TASKS[name]
        t0 = time.perf_counter()
        env = gym.make_vec(task.env_id, num_envs=num_envs)
        obs, info = env.reset(seed=seed)
        frames, paths = [], []
        sheet = []
        final = None
        for t in range(env.episode_length):
            action = task.expert(env, info)
            obs, _, _, _, info = env.step(action)
            if "final_info" in info:
                final = info["final_info"]
                img = task.image(info["final_obs"])
            else:
                img = task.image(obs)
            paths.append(task.track(env, info) if final is None else paths[-1])
            frame = (task.frame or _frame)(env, img, np.array(paths))
            frames.append(frame)
            if t % max(1, env.episode_length // 8) == 0 or final is not None:
                sheet.append((t + 1, img.cpu().numpy()))
        if final is None:
            raise RuntimeError(f"{name}: the episode did not end within {env.episode_length} steps")
        metrics = {
            k: (float(final[k].float().mean()), float(final[k].float().std()))
            for k in (*task.metrics, "return")
        }
        results[name] = {"envs": num_envs, "seconds": time.perf_counter() - t0, "metrics": metrics}
        _write_sheet(out / f"{name}_frames.png", sheet, name)
        _write_video(out / f"{name}.mp4", frames)
        log(f"{name}: {', '.join(f'{k} {m:.2f} ± {s:.2f}' for k, (m, s) in metrics.items())}")
    (out / "metrics.json").write_text(json.dumps(results, indent=1))
    (out / "metrics.md").write_text(_markdown(results))
    log(f"wrote {out}/metrics.md, metrics.json, *_frames.png, *.mp4")
    return results


def _topdown(env, path: np.ndarray, size: int = 200, span: float = 0.1) -> np.ndarray:
    """RGB top-down view (x right, z up) of the back around env 0's goal: skin height, the
    probe's path (red), its current footprint (yellow) and the goal (green)."""
    g = env.goal_cmd[0].cpu().numpy()
    xs = g[0] + np.linspace(-span, span, size)
    zs = g[1] + np.linspace(span, -span, size)
    xx, zz = np.meshgrid(xs, zs)
    pid = torch.zeros(xx.shape, dtype=torch.long, device=env.device)
    h = env.scene.skin.height(
        torch.tensor(xx, device=env.device), torch.tensor(zz, device=env.device), pid
    )
    h = h.cpu().numpy()
    gray = (h - h.min()) / max(h.max() - h.min(), 1e-9)
    img = (np.stack([gray] * 3, -1) * 160 + 40).astype(np.uint8)

    def px(x, z):
        i = np.clip(((g[1] + span - z) / (2 * span) * (size - 1)).round().astype(int), 0, size - 1)
        j = np.clip(((x - g[0] + span) / (2 * span) * (size - 1)).round().astype(int), 0, size - 1)
        return i, j

    i, j = px(path[:, 0], path[:, 2])
    img[i, j] = (230, 40, 40)
    gi, gj = px(np.array([g[0]]), np.array([g[1]]))
    img[max(gi[0] - 3, 0) : gi[0] + 4, gj[0]] = (40, 220, 40)
    img[gi[0], max(gj[0] - 3, 0) : gj[0] + 4] = (40, 220, 40)
    rot = env.scene.probe_rot[0].cpu().numpy()
    p = env.scene.probe_pos[0].cpu().numpy()
    for s in np.linspace(-0.0375, 0.0375, 40):
        fi, fj = px(np.array([p[0] + s * rot[0, 0]]), np.array([p[2] + s * rot[2, 0]]))
        img[fi, fj] = (240, 220, 40)
    return img


def _frame(env, us: torch.Tensor, path: np.ndarray) -> np.ndarray:
    u = (us.clamp(0, 1) * 255).to(torch.uint8).cpu().numpy()
    u = np.repeat(u[..., None], 3, -1)
    top = _topdown(env, path, size=u.shape[0])
    frame = np.concatenate([u, np.zeros((u.shape[0], 4, 3), np.uint8), top], 1)
    frame = frame.repeat(2, 0).repeat(2, 1)
    pad_w = (-frame.shape[1]) % 16
    pad_h = (-frame.shape[0]) % 16
    return np.pad(frame, ((0, pad_h), (0, pad_w), (0, 0)))


def _write_video(path: Path, frames: list[np.ndarray], fps: int = 30) -> None:
    import imageio.v2 as imageio

    with imageio.get_writer(path, fps=fps, codec="libx264", quality=7) as w:
        for f in frames:
            w.append_data(f)


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
        ax.set_title(f"{name}, step {t}")
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def _markdown(results: dict) -> str:
    lines = ["| task | metric | mean | std |", "|---|---|---|---|"]
    for task, r in results.items():
        for k, (m, s) in r["metrics"].items():
            lines.append(f"| {task} | {k} | {m:.3f} | {s:.3f} |")
    return "\n".join(lines) + "\n"
