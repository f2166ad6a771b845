"""Show what was saved, without simulating it again: a run's evaluation episodes
(``sonogym view --run``) and a recorded LeRobot dataset's episodes (``sonogym view --dataset``).

A run's episode log (``episodes/<protocol>.npz``, ``sonogym.evaluation.episodes``) holds the
tracked point of each episode (``TaskSpec.track``): a probe task's surface command relative to
its goal command (x, z in mm, yaw and tilt in deg), or surgery's drill tip in {G} (mm). The
viewer builds the episode's patient and its env (not stepped: only its goal and, for surgery,
the still probe's nominal pose and the plan are read), meshes the patient, and places the probe
or the drill tip along the track; images are not in the log.

A dataset holds what a policy learns from: the images, the numeric features (state, action)
per frame, shown as 2-D images and series; a pose feature (names x, y, z, qw, qx, qy, qz) is
also drawn as a frame with its path in 3-D (surgery's drill tip in the probe frame {U}).
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import rerun as rr
import torch

from sonogym.envs.base import make_config
from sonogym.envs.patients import resolve_patients
from sonogym.envs.registry import get_task, make_vec
from sonogym.evaluation.episodes import EpisodeLog, episode_patient, load_log, log_path
from sonogym.geometry import matrix_from_quat
from sonogym.runs import lists_to_tuples
from sonogym.viewer import draw
from sonogym.viewer.env_view import ViewResult
from sonogym.viewer.geometry import image_quads, patient_surfaces, to_frame

#: Track units -> SI factor.
_SI = {"mm": 1e-3, "m": 1.0, "deg": math.pi / 180, "rad": 1.0}
#: Names of a numeric feature that is a pose: position (m) + quaternion (w, x, y, z).
POSE_NAMES = ("x", "y", "z", "qw", "qx", "qy", "qz")


def load_run_log(run: str | Path, protocol: str) -> EpisodeLog:
    """The run's episode log of ``protocol``, naming the logs it has when there is none."""
    path = log_path(run, protocol)
    run = Path(run)
    if not (run / "config.json").is_file() and not (run / "episodes").is_dir():
        raise FileNotFoundError(
            f"{run} is not a run folder (no config.json, no episodes/): give --run a folder "
            "that sonogym train or il-train wrote and sonogym eval evaluated"
        )
    if not path.is_file():
        have = sorted(p.stem for p in (Path(run) / "episodes").glob("*.npz"))
        raise FileNotFoundError(
            f"{path} not found: the run has episode logs {have or 'none'}; "
            f"`sonogym eval --run {run}` writes them"
        )
    return load_log(path)


def view_run_episode(
    rec: rr.RecordingStream,
    run: str | Path,
    protocol: str = "idt",
    episode: int = 0,
    controller: str | None = None,
    log=print,
) -> ViewResult:
    """Log episode ``episode`` of ``controller`` (default: the run's policy) from the run's
    ``protocol`` log: the patient, the goal and the probe or drill tip along the saved track
    (timeline 0..T, one point per state), the track's columns as series and the episode's
    metrics as a text summary."""
    ep_log = load_run_log(run, protocol)
    meta = ep_log.meta
    controller = controller or (
        "policy" if "policy" in ep_log.tracks else next(iter(ep_log.tracks))
    )
    if controller not in ep_log.tracks:
        raise ValueError(f"{ep_log.path} has no controller {controller!r}: {list(ep_log.tracks)}")
    tracks = ep_log.tracks[controller]
    if not 0 <= episode < len(tracks):
        raise ValueError(f"episode {episode}: {ep_log.path} holds episodes 0..{len(tracks) - 1}")
    task, track = meta["task"], tracks[episode]
    cols, units = meta["track_columns"], meta["track_units"]
    si = track * np.array([_SI[u] for u in units])
    spec = get_task(task)
    options = {
        **lists_to_tuples(meta.get("test_env", {})),
        "imaging_randomization": False,
        "patients": (episode_patient(ep_log, episode),),
        "device": "cpu",
    }
    cfg = make_config(spec.config_cls, options)
    log(f"{task}: episode {episode} of {controller} ({protocol}), patient {cfg.patients[0]}")
    patient = resolve_patients([cfg.patients[0]], cfg.phantom_spacing)[0]
    meshes = patient_surfaces(patient.labels.numpy(), patient.affine, cfg.target_vertebra)
    env = make_vec(task, 1, **options)
    plan = None
    if "yaw" not in cols:  # a drill-tip track: the plan it is measured against
        plan = patient.landmarks.trajectory(cfg.target_vertebra, cfg.side)
    del patient

    draw.log_frame_conventions(rec)
    draw.log_surfaces(rec, meshes)
    series = {f"series/{c}": [f"{c} ({u})"] for c, u in zip(cols, units, strict=True)}
    draw.log_series_names(rec, series)
    metrics = {k: float(v[episode]) for k, v in ep_log.metrics[controller].items()}
    rec.log(
        "summary",
        rr.TextDocument(
            _summary(meta, controller, episode, metrics), media_type=rr.MediaType.MARKDOWN
        ),
        static=True,
    )
    sc = env.scene
    quads = image_quads(sc.probe_geometry)
    if plan is not None:
        g_pos, g_rot = _first_env(sc.goal_pos, sc.goal_rot)
        draw.log_surgery_plan(
            rec, g_pos, g_rot, plan.entry, plan.target, float(env.half_width[0]), cfg.skin_distance
        )
        draw.log_pose(rec, "world/probe", *_first_env(sc.probe_pos, sc.probe_rot), static=True)
        draw.log_image_outlines(rec, quads)
        points = to_frame(g_pos, g_rot, si)  # the tip in {P}
        for t, p in enumerate(points):
            draw.set_step(rec, t)
            draw.log_points(rec, "world/drill", p[None], draw.DRILL_COLOR, radius=0.002)
            draw.log_polyline(rec, "world/drill_path", points[: t + 1], draw.DRILL_COLOR)
            draw.log_scalars(rec, {k: v for k, v in zip(series, track[t], strict=True)})
    else:
        if hasattr(env, "goal_rot"):
            draw.log_pose(rec, "world/goal", *_first_env(env.goal_pos, env.goal_rot), static=True)
        draw.log_image_outlines(rec, quads)
        goal = env.goal_cmd[0].double().cpu().numpy()
        cmd = torch.as_tensor(goal[: len(cols)] + si, dtype=torch.float32)  # x, z, yaw[, tilt]
        pos, rot = sc.surface_pose(cmd.to(env.device))
        pos, rot = pos.cpu().numpy(), rot.cpu().numpy()
        for t in range(len(track)):
            draw.set_step(rec, t)
            draw.log_pose(rec, "world/probe", pos[t], rot[t])
            draw.log_polyline(rec, "world/probe_path", pos[: t + 1], draw.PROBE_PATH_COLOR)
            draw.log_scalars(rec, {k: v for k, v in zip(series, track[t], strict=True)})
    centre = sc.target_centres[0].double().cpu().numpy()
    normal = draw.AXIAL if plan is not None else rot[0][:, 1]  # the start's image plane
    eye = (centre + draw.eye_offset(normal), centre)
    env.close()
    rec.send_blueprint(draw.blueprint([], list(series), eye, text="summary"))
    return ViewResult(len(track), [], list(series))


def _summary(meta: dict[str, Any], controller: str, episode: int, metrics: dict) -> str:
    lines = [
        f"# {meta['task']}: episode {episode} of {controller}",
        "",
        f"run `{meta['run']}` ({meta['algo']}, seed {meta['train_seed']}), protocol "
        f"`{meta['protocol']}`, evaluation seed {meta['eval_seed']}, checkpoint "
        f"`{meta['checkpoint']}`",
        "",
        "| metric | value |",
        "|---|---|",
        *(f"| {k} | {v:.4g} |" for k, v in metrics.items()),
    ]
    return "\n".join(lines)


def view_dataset_episode(
    rec: rr.RecordingStream, root: str | Path, episode: int = 0, log=print
) -> ViewResult:
    """Log dataset episode ``episode``: each image feature as a 2-D image and each numeric
    feature as a series over its frames (timeline = ``frame_index``); a pose feature also as a
    frame and path in 3-D."""
    from sonogym.imitation import lerobot_format as fmt
    from sonogym.imitation.reader import LeRobotFrames

    frames = LeRobotFrames(root, episodes=[episode])  # IndexError names the episodes it holds
    feats = {k: v for k, v in frames.features.items() if k not in fmt.DEFAULT_FEATURES}
    images = {k: "image/" + k.removeprefix("observation.images.") for k in frames.image_keys}
    numeric = {k: f"series/{k}" for k in feats if k not in images}
    poses = [k for k in numeric if tuple(feats[k].get("names") or ()) == POSE_NAMES]
    meta_path = Path(root) / "meta" / "sonogym.json"
    about = json.loads(meta_path.read_text()) if meta_path.is_file() else {}
    log(
        f"dataset {root}: episode {episode}, {len(frames)} frames"
        + (f" ({about['task']})" if "task" in about else "")
    )
    draw.log_series_names(
        rec, {p: [str(n) for n in (feats[k].get("names") or [k])] for k, p in numeric.items()}
    )
    paths: dict[str, list[np.ndarray]] = {k: [] for k in poses}
    for i in range(len(frames)):
        item = frames[i]
        draw.set_step(rec, int(item["frame_index"]))
        for k, path in images.items():
            img = item[k].numpy()  # (C, H, W) in [0, 1]
            rec.log(path, rr.Image((np.moveaxis(img, 0, -1) * 255).round().astype(np.uint8)))
        draw.log_scalars(rec, {p: item[k].numpy().ravel() for k, p in numeric.items()})
        for k in poses:
            v = item[k].double()
            rot = matrix_from_quat(v[3:][None])[0].numpy()
            draw.log_pose(rec, f"world/{k}", v[:3].numpy(), rot, 0.01)
            paths[k].append(v[:3].numpy())
            draw.log_polyline(rec, f"world/{k}_path", np.array(paths[k]), draw.DRILL_COLOR)
    rec.log(
        "summary", rr.TextDocument(json.dumps(about, indent=1) if about else str(root)), static=True
    )
    rec.send_blueprint(
        draw.blueprint(
            list(images.values()), list(numeric.values()), text="summary", scene=bool(poses)
        )
    )
    return ViewResult(len(frames), list(images.values()), list(numeric.values()))


def _first_env(*tensors: torch.Tensor) -> list[np.ndarray]:
    """Env 0's rows as numpy arrays (the replay shows env 0)."""
    return [t[0].cpu().numpy() for t in tensors]
