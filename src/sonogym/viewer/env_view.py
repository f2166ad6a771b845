"""Step a task's env under a policy and stream env 0 to Rerun (``sonogym view --task``).

Every source of the scene is the env's public state, read the same way for each task: the
probe pose ``scene.probe_pos/probe_rot``, its images ``scene.observe("us"/"labels")``, the arms
a scene holds (``arm`` + ``q``; ``probe_arm`` + ``q_probe``; ``drill_arm`` + ``q_drill``), a
goal frame (``env.goal_pos/goal_rot`` or ``env.scene.goal_pos/goal_rot``), a drill tip
(``scene.tip_pos/tip_rot``) and a reconstruction volume (``env.volume``, voxels of
``cfg.voxel_size`` from ``env.centre - cfg.cube_half_extent``). The patient's surfaces come
from its label map, loaded before the env is built (the env keeps no full volume).

The ``step`` timeline counts env steps: 0 is the start state after ``reset``, k the state after
k steps (an autoreset's new start where an episode ended); the reward and metrics logged at k
are those of step k (an ended episode's metrics from its ``final_info``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import rerun as rr
import torch

from sonogym.envs.base import make_config
from sonogym.envs.patients import resolve_patients
from sonogym.envs.policy import ExpertPolicy, RandomPolicy
from sonogym.envs.registry import get_task, make_vec
from sonogym.envs.rollout import rollout
from sonogym.viewer import draw
from sonogym.viewer.geometry import (
    arm_joint_origins,
    image_quads,
    patient_surfaces,
    voxel_centres,
)

#: (scene attribute of an arm, of its joints, entity name).
ARMS = (
    ("arm", "q", "probe_arm"),
    ("probe_arm", "q_probe", "probe_arm"),
    ("drill_arm", "q_drill", "drill_arm"),
)
BUILT_IN = ("expert", "random")


@dataclass(frozen=True)
class PolicyChoice:
    """Who acts: ``expert`` (the task's expert or heuristic), ``random``, or a trained ``run``
    folder (RL or IL; a shipped pretrained policy is its folder and weights file)."""

    kind: str  # "expert", "random" or "run"
    run: Path | None = None
    checkpoint: Path | None = None


def policy_choice(policy: str, pretrained: str | None = None) -> PolicyChoice:
    """``--policy expert|random|RUN`` or ``--pretrained NAME`` -> ``PolicyChoice``; names the
    options when ``policy`` is none of them."""
    if pretrained is not None:
        from sonogym.evaluation.pretrained import pretrained_dir, weights

        return PolicyChoice("run", pretrained_dir(pretrained), weights(pretrained))
    if policy in BUILT_IN:
        return PolicyChoice(policy)
    if not Path(policy).is_dir():
        raise ValueError(
            f"policy {policy!r} is neither {' nor '.join(BUILT_IN)} nor a run folder "
            "(sonogym train / il-train); for a shipped policy give --pretrained NAME"
        )
    return PolicyChoice("run", Path(policy))


def resolve_env(
    task: str | None, choice: PolicyChoice, options: dict[str, Any]
) -> tuple[str, dict[str, Any]]:
    """The task and env options of a view: a run's task and training env (images as simulated,
    as evaluation shows them, on the CPU) under ``options``; otherwise ``task`` with
    ``options``."""
    if choice.kind != "run":
        if task is None:
            raise ValueError("give --task (navigation, reconstruction or surgery) or a run")
        get_task(task)
        return task, dict(options)
    from sonogym.evaluation.trained import load_run

    run = load_run(choice.run)
    if task is not None and task != run.task:
        raise ValueError(f"{choice.run} is a {run.task} run, not {task}: leave out --task")
    # on the CPU, where run_policy puts the policy
    return run.task, {**run.evaluation_env_kwargs(), "device": "cpu", **options}


def make_policy(choice: PolicyChoice, task: str, env, seed: int):
    if choice.kind == "expert":
        return ExpertPolicy(env, get_task(task).expert)
    if choice.kind == "random":
        return RandomPolicy(env, seed)
    from sonogym.evaluation.trained import load_run, run_policy

    return run_policy(load_run(choice.run), env, choice.checkpoint)


@dataclass
class ViewResult:
    """What a view logged: ``timeline`` points on the ``step`` timeline (0 .. timeline - 1:
    an env view's start state and its steps, an episode log's states, a dataset's frames), the
    image and series entities, and the metrics of the episodes that ended."""

    timeline: int
    images: list[str]
    series: list[str]
    episodes: list[dict[str, float]] = field(default_factory=list)
    last: dict[str, float] = field(default_factory=dict)  # the metrics logged at the last step


def view_env(
    rec: rr.RecordingStream,
    task: str,
    choice: PolicyChoice,
    options: dict[str, Any],
    steps: int | None = None,
    seed: int = 0,
    log: Callable[[str], None] = print,
    progress: bool = False,
) -> ViewResult:
    """Run ``choice``'s policy in one env of ``task`` (env ``options``) for ``steps`` steps
    (default: ``episode_length - 1``, one episode up to its last state) from ``reset(seed)``,
    logging env 0 to ``rec`` (see the module doc). ``progress``: show the env's patients
    loading and the steps on stderr (``sonogym.progress``)."""
    from sonogym.evaluation.rl_eval import showing_patients
    from sonogym.progress import progress_bar

    spec = get_task(task)
    cfg = make_config(spec.config_cls, options)
    log(f"{task}: loading patient {cfg.patients[0]} and meshing its labels")
    patient = resolve_patients([cfg.patients[0]], cfg.phantom_spacing)[0]
    meshes = patient_surfaces(patient.labels.numpy(), patient.affine, cfg.target_vertebra)
    with showing_patients(task, options, progress):
        env = make_vec(task, 1, **options)  # shares the loaded patient while it is held
    plan = None
    if hasattr(env.scene, "tip_pos"):  # a drill: its planned trajectory
        plan = patient.landmarks.trajectory(cfg.target_vertebra, cfg.side)
    del patient
    policy = make_policy(choice, task, env, seed)
    # one episode up to its last state: the step that ends an episode resets the env, so the
    # state after it is the next episode's start
    steps = max(1, env.episode_length - 1) if steps is None else steps
    if steps < 1:
        raise ValueError(f"steps must be >= 1, got {steps}")

    scene = EnvScene(rec, env)
    series = {"series/reward": ["reward"]}
    series |= {f"series/{m.key}": [f"{m.label} ({m.unit})"] for m in spec.metrics}
    draw.log_frame_conventions(rec)
    draw.log_surfaces(rec, meshes)
    rec.log("image/labels", draw.label_annotations(), static=True)
    if plan is not None:
        g_pos, g_rot = env.scene.goal_pos[0].cpu().numpy(), env.scene.goal_rot[0].cpu().numpy()
        draw.log_surgery_plan(
            rec, g_pos, g_rot, plan.entry, plan.target, float(env.half_width[0]), cfg.skin_distance
        )
    obs, info = env.reset(seed=seed)
    if "safe" in info:
        series["series/safe"] = ["safe (in C_free or C_drill)"]
    draw.log_series_names(rec, series)
    draw.set_step(rec, 0)
    scene.log_state(new_episode=True)
    rec.send_blueprint(draw.blueprint(scene.image_paths, list(series), scene.eye()))
    result = ViewResult(steps + 1, scene.image_paths, list(series))
    metric_scale = {m.key: m.scale for m in spec.metrics}
    bar = progress_bar(steps, f"{task} view", unit="step", enabled=progress)
    for step in rollout(env, policy, steps, reset=False, obs=obs, info=info):
        bar.update(1)
        draw.set_step(rec, step.t + 1)
        ended = bool(step.done[0])
        if ended:
            row = step.final_info["env_ids"].tolist().index(0)
            metrics = {k: v[row] for k, v in step.final_info.items() if k != "env_ids"}
            result.episodes.append({k: float(v) for k, v in metrics.items()})
        else:
            metrics = {k: v[0] for k, v in env.current_metrics(scene.env0).items()}
        values = {"series/reward": float(step.reward[0])}
        values |= {
            f"series/{k}": float(v) * s
            for k, s in metric_scale.items()
            if (v := metrics.get(k)) is not None
        }
        if "safe" in step.next_info:
            values["series/safe"] = float(step.next_info["safe"][0])
        draw.log_scalars(rec, values)
        scene.log_state(new_episode=ended)
        result.last = {k: float(v) for k, v in metrics.items()}
    bar.close()
    env.close()
    return result


class EnvScene:
    """Logs env 0's state (see the module doc); keeps the paths of the current episode and the
    last images logged (a still probe's images are logged once per episode)."""

    def __init__(self, rec: rr.RecordingStream, env) -> None:
        self.rec, self.env, self.scene = rec, env, env.scene
        self.env0 = torch.zeros(1, dtype=torch.long, device=env.device)
        self.quads = image_quads(self.scene.probe_geometry)
        n = len(self.quads)
        self.image_paths = draw.slice_paths("image/us", n) + draw.slice_paths("image/labels", n)
        self.arms = [
            (name, getattr(self.scene, a), q)
            for a, q, name in ARMS
            if hasattr(self.scene, a) and hasattr(self.scene, q)
        ]
        self.goal = env if hasattr(env, "goal_rot") else None
        self.drill = hasattr(self.scene, "tip_pos")
        if self.drill:
            self.goal = None  # drawn with the plan
        self.volume = isinstance(getattr(env, "volume", None), torch.Tensor)
        self.probe_path: list[np.ndarray] = []
        self.drill_path: list[np.ndarray] = []
        self._last_us: torch.Tensor | None = None

    def eye(self) -> tuple[np.ndarray, np.ndarray]:
        """The 3-D view's eye (position, target): looking at the target vertebra's centre,
        facing the probe's image plane as it is now (a drill scene: along the spine)."""
        target = self.scene.target_centres[0].double().cpu().numpy()
        normal = draw.AXIAL if self.drill else self.scene.probe_rot[0, :, 1].cpu().numpy()
        return target + draw.eye_offset(normal), target

    def log_state(self, new_episode: bool) -> None:
        rec, sc, ids = self.rec, self.scene, self.env0
        if new_episode:
            self.probe_path, self.drill_path = [], []
        pos, rot = sc.probe_pos[0].cpu().numpy(), sc.probe_rot[0].cpu().numpy()
        draw.log_pose(rec, "world/probe", pos, rot)
        self.probe_path.append(pos)
        draw.log_polyline(rec, "world/probe_path", np.array(self.probe_path), draw.PROBE_PATH_COLOR)
        us = sc.observe("us", ids)[0].float().cpu()
        if self._last_us is None or not torch.equal(us, self._last_us):
            labels = sc.observe("labels", ids)[0].cpu().numpy()
            draw.log_image_planes(rec, self.quads, us.numpy())
            draw.log_images_2d(rec, us.numpy(), labels)
            self._last_us = us
        for name, arm, q in self.arms:
            joints = arm_joint_origins(arm, getattr(sc, q))
            draw.log_arm(rec, f"world/{name}", joints, draw.ARM_COLORS.get(arm.config.model))
        if self.goal is not None:
            draw.log_pose(
                rec,
                "world/goal",
                self.goal.goal_pos[0].cpu().numpy(),
                self.goal.goal_rot[0].cpu().numpy(),
            )
        if self.drill:
            tip, tip_rot = sc.tip_pos[0].cpu().numpy(), sc.tip_rot[0].cpu().numpy()
            draw.log_pose(rec, "world/drill", tip, tip_rot, 0.02)
            self.drill_path.append(tip)
            draw.log_polyline(rec, "world/drill_path", np.array(self.drill_path), draw.DRILL_COLOR)
        if self.volume:
            cfg = self.env.cfg
            corner = self.env.centre[0].double().cpu().numpy() - cfg.cube_half_extent
            pts = voxel_centres(self.env.volume[0], corner, cfg.voxel_size)
            draw.log_points(rec, "world/reconstruction", pts, draw.POINTS_COLOR)
