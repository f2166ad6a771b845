"""Expert datasets: roll a task's expert out in batched envs and write a LeRobotDataset v3.0.

``record(task, out, ...)`` runs ``ceil(episodes / envs)`` batches of fixed-length episodes
through the rollout loop (``sonogym.envs.rollout``), each batch from its own seed
(``seed + batch``), and writes every episode the task's ``DatasetSpec.success`` accepts (a
failed expert episode is counted in ``meta/sonogym.json``, not written). A frame holds the
observation the expert acted on (the task's dataset features, images quantised to 8 bits as
``quantize_images`` does) and the action it took, in the env's action units.

Safe writing: episodes land whole or not at all (``DatasetWriter``); ``meta/sonogym.json``
(task, recipe, env options, seed, envs, batches done, episodes written and failed) is written
before the first batch and after each batch. ``resume`` continues an interrupted recording
(interrupted in its first batch too): it reruns the interrupted batch (batches are
deterministic) and skips the episodes that batch had already written, so nothing is duplicated
or missing; ``force`` replaces an existing dataset. The output-folder rule (the folder's
marker and lock) is ``sonogym.runs.prepare_output``'s.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from sonogym.envs.identity import identity, stamp
from sonogym.envs.policy import ExpertPolicy
from sonogym.envs.registry import get_task, make_vec
from sonogym.envs.rollout import rollout
from sonogym.imitation.lerobot_format import encode_png
from sonogym.imitation.processor import PolicyFeatures
from sonogym.imitation.task_datasets import dataset_spec
from sonogym.imitation.writer import DatasetWriter
from sonogym.progress import progress_bar
from sonogym.runs import (
    atomic_write_json,
    deleted_message,
    lists_to_tuples,
    prepare_output,
    read_json,
    to_jsonable,
)

META = "meta/sonogym.json"
#: info.json's field with the benchmark identity the dataset was recorded under
IDENTITY_INFO_KEY = "sonogym_identity"
#: env options an evaluation of a policy trained on the dataset reuses (what it imaged); the
#: start randomisation of data collection is not among them
EVAL_ENV_KEYS = ("patients", "simulator", "learned_nets", "phantom_spacing", "side")


@dataclass(frozen=True)
class RecordResult:
    out: Path
    episodes: int  # episodes in the dataset
    failed: int  # expert episodes not written (not successful), in all batches so far
    frames: int
    seconds: float  # this call's wall time


def info_features(task: str, action_dim: int) -> dict[str, dict[str, Any]]:
    """The dataset's features in LeRobot's ``info.json`` form (images (H, W, C))."""
    spec = get_task(task)
    out = {}
    for f in dataset_spec(task).features:
        if f.dtype == "image":
            c, h, w = f.shape
            out[f.key] = {"dtype": "image", "shape": [h, w, c],
                          "names": ["height", "width", "channels"]}  # fmt: skip
        else:
            out[f.key] = {"dtype": "float32", "shape": list(f.shape), "names": list(f.names)}
    out["action"] = {"dtype": "float32", "shape": [action_dim], "names": list(spec.action_names)}
    return out


def check_task_features(task: str, features: PolicyFeatures, where: str) -> None:
    """Refuse features (a dataset's, or those a run was trained on) that are not ``task``'s
    dataset features: a policy trained on them cannot act in the task's env. ``where`` names
    what says the task (a dataset folder, a run's config.json)."""
    spec = get_task(task)  # an unknown task is named with the known ones
    want = PolicyFeatures.from_info(info_features(task, len(spec.action_names)))
    if features != want:
        raise ValueError(
            f"{where} names task {task!r}, but the features {features.to_dict()} are not "
            f"{task}'s {want.to_dict()}: a policy trained on them cannot act in the {task} env. "
            "Train on a dataset recorded for the task (sonogym record --task ...), or correct "
            "the task named there"
        )


def quantize_images(x: torch.Tensor) -> torch.Tensor:
    """Float images in [0, 1] -> uint8 ``round(x * 255)``, the datasets' 8-bit storage."""
    return (x.clamp(0, 1) * 255).round().to(torch.uint8)


def obs_to_features(task: str) -> Callable[[Any, dict], dict[str, torch.Tensor]]:
    """The env observation -> dataset features of ``task`` as an IL policy sees them: images
    (N, C, H, W) float in [0, 1], quantised to 8 bits exactly as the dataset stores them."""
    feats = dataset_spec(task).features

    def convert(obs, info) -> dict[str, torch.Tensor]:
        out = {}
        for f in feats:
            x = f.fn(obs, info)
            out[f.key] = quantize_images(x).float() / 255 if f.dtype == "image" else x.float()
        return out

    return convert


def record(
    task: str,
    out: str | Path,
    episodes: int | None = None,
    recipe: str | None = None,
    envs: int | None = None,
    env_kwargs: dict[str, Any] | None = None,
    seed: int | None = None,
    resume: bool = False,
    force: bool = False,
    progress: bool = True,
    log: Callable[[str], None] = print,
) -> RecordResult:
    """Record ``episodes`` expert episodes of ``task`` into ``out`` (see the module doc).

    ``recipe``: one of the task's dataset recipes (``DatasetSpec.recipes`` in
    ``sonogym.tasks.<task>.dataset``: its env options and, unless ``episodes`` is given, its
    episode count); ``env_kwargs`` add to / override them."""
    dataset_spec(task)  # refuses a task without datasets
    default_mode = get_task(task).default_obs_mode
    if (env_kwargs or {}).get("obs_mode", default_mode) != default_mode:
        # the dataset's features (spec.features) read the default observation
        raise ValueError(
            f"{task} datasets record the default observation (obs_mode={default_mode!r}), got "
            f"obs_mode={env_kwargs['obs_mode']!r}; leave obs_mode out of the env options"
        )
    if (env_kwargs or {}).get("force_action"):
        # the dataset's actions are the task's (spec.action_names); a fixed contact_force is fine
        raise ValueError(
            f"{task} datasets record the task's actions {get_task(task).action_names}; "
            "force_action adds one they do not name: leave it out (a fixed contact_force works)"
        )
    out = Path(out)
    if resume and not (out / META).is_file():
        raise FileNotFoundError(f"nothing to resume: {out} holds no sonogym recording")
    if not resume:
        envs = 16 if envs is None else envs
        if envs < 1:
            raise ValueError(f"envs must be a positive integer, got {envs}")
        if episodes is not None and episodes < 1:
            raise ValueError(f"episodes must be a positive integer, got {episodes}")
    with prepare_output(out, resume=resume, force=force, kind="dataset") as folder:
        if folder.deleted:
            log(deleted_message(out, folder.deleted))
        return _record(task, out, episodes, recipe, envs, env_kwargs, seed, resume, progress, log)


def _record(task, out, episodes, recipe, envs, env_kwargs, seed, resume, progress, log):
    spec = dataset_spec(task)
    t0 = time.perf_counter()
    if resume:
        meta = read_json(out / META, "sonogym recording", ("task", "env_kwargs", "envs", "seed"))
        if "preset" in meta:  # recordings before the recipe had its name
            meta["recipe"] = meta.pop("preset")
        given = {"task": task, "recipe": recipe, "envs": envs, "seed": seed,
                 "env_kwargs": env_kwargs or None}  # fmt: skip
        clash = [k for k, v in given.items() if v is not None and to_jsonable(v) != meta.get(k)]
        if clash:
            raise ValueError(
                f"cannot resume {out} with options that differ from its recording: {clash} "
                f"(recording: { {k: meta.get(k) for k in clash} }); drop them or use --force"
            )
        episodes = episodes or meta["episodes_wanted"]
        kw = lists_to_tuples(meta["env_kwargs"])
        envs, seed, recipe = meta["envs"], meta["seed"], meta.get("recipe")
    else:
        seed = 0 if seed is None else seed
        kw = dict(spec.recipe(recipe).env_kwargs) if recipe else {}
        kw.update(env_kwargs or {})
        if episodes is None:
            episodes = spec.recipe(recipe).episodes if recipe else 100
        meta = {"task": task, "recipe": recipe, "envs": envs, "seed": seed,
                "env_kwargs": to_jsonable(kw), "episodes_wanted": episodes, "batches_done": 0,
                "episodes_written": 0, "failed": 0}  # fmt: skip
    if episodes < 1:
        raise ValueError(f"episodes must be a positive integer, got {episodes}")
    meta["episodes_wanted"] = episodes
    meta["eval_env_kwargs"] = to_jsonable({k: v for k, v in kw.items() if k in EVAL_ENV_KEYS})
    made_with = identity(task, kw)
    if resume and meta.get("identity") not in (None, made_with):
        raise ValueError(
            f"cannot resume {out}: it was recorded under another benchmark identity "
            f"({stamp(meta['identity'])}; now {stamp(made_with)}); record it anew with --force"
        )
    meta["identity"] = made_with

    env = make_vec(task, envs, **kw)
    a_dim = env.single_action_space.shape[0]
    # how it is recorded is on disk before the dataset's first file: a recording interrupted
    # anywhere, in its first batch too, resumes
    atomic_write_json(out / META, meta)
    writer = DatasetWriter(out, spec.fps, info_features(task, a_dim), spec.instruction,
                           spec.robot_type, resume=resume)  # fmt: skip
    writer.set_info(IDENTITY_INFO_KEY, made_with)
    done_eps = writer.num_episodes
    if done_eps >= episodes:
        log(f"{out} already holds {done_eps} >= {episodes} episodes; nothing to record")
        return RecordResult(out, done_eps, meta["failed"], writer.num_frames, 0.0)
    # a batch interrupted after some of its episodes were written is rerun, those skipped
    skip = done_eps - meta["episodes_written"]
    per_ep = _bytes_per_episode(env, task, envs)
    log(
        f"{task}: recording {episodes - done_eps} expert episodes of {env.episode_length} steps "
        f"with {envs} envs ({kw or 'default options'}) into {out}; about "
        f"{per_ep / 2**20:.1f} MiB per episode, {per_ep * (episodes - done_eps) / 2**30:.2f} GiB "
        "to write"
    )
    bar = progress_bar(episodes, f"record {task}", initial=done_eps, unit="episode",
                       enabled=progress)  # fmt: skip
    policy = ExpertPolicy(env, get_task(task).expert)
    fruitless = 0  # batches in a row that wrote nothing
    while writer.num_episodes < episodes:
        b = meta["batches_done"]
        written, failed = _record_batch(env, policy, task, writer, seed + b, skip,
                                        episodes - writer.num_episodes)  # fmt: skip
        bar.update(written)
        skip = 0
        meta.update(batches_done=b + 1, episodes_written=writer.num_episodes,
                    failed=meta["failed"] + failed)  # fmt: skip
        atomic_write_json(out / META, meta)
        fruitless = 0 if written else fruitless + 1
        if fruitless >= 10:
            raise RuntimeError(
                f"the {task} expert failed every episode of 10 batches in a row with {kw}: "
                "check the env options (patients, simulator) or the subject's corridor"
            )
    bar.close()
    env.close()
    res = RecordResult(out, writer.num_episodes, meta["failed"], writer.num_frames,
                       time.perf_counter() - t0)  # fmt: skip
    log(f"wrote {res.episodes} episodes ({res.frames} frames) to {out}; {res.failed} failed "
        "expert episodes were not written")  # fmt: skip
    return res


def _record_batch(env, policy, task: str, writer, seed: int, skip: int, room: int):
    """One batch of ``env.num_envs`` episodes from ``env.reset(seed)``; writes the successful
    ones (after skipping the first ``skip`` of them, already written) up to ``room``."""
    spec = dataset_spec(task)
    n, t_len = env.num_envs, env.episode_length
    frames: dict[str, list[torch.Tensor]] = {f.key: [] for f in spec.features}
    frames["action"] = []
    final = None
    for step in rollout(env, policy, t_len, seed=seed):
        for f in spec.features:
            x = f.fn(step.obs, step.info)
            frames[f.key].append(quantize_images(x).cpu() if f.dtype == "image" else x.cpu())
        frames["action"].append(step.action.detach().float().cpu())
        if step.final_info is not None:
            final = step.final_info
    if final is None or len(final["env_ids"]) != n:
        raise RuntimeError(f"{task}: the batch's episodes did not all end after {t_len} steps")
    order = torch.argsort(final["env_ids"].cpu())
    ok = spec.success({k: v.cpu()[order] for k, v in final.items() if k != "env_ids"})
    stacked = {k: torch.stack(v, 1) for k, v in frames.items()}  # (N, T, ...)
    written = 0
    kept = 0
    for i in range(n):
        if not bool(ok[i]):
            continue
        kept += 1
        if kept <= skip:
            continue
        if written >= room:
            break
        writer.add_episode({k: v[i].numpy() for k, v in stacked.items()})
        written += 1
    return written, int((~ok).sum())


def _bytes_per_episode(env, task: str, envs: int) -> float:
    """Estimated bytes of one episode on disk: one start frame's PNGs and numbers, times the
    episode length (ultrasound frames compress alike along an episode)."""
    obs, info = env.reset(seed=0)
    size = 0.0
    for f in dataset_spec(task).features:
        x = f.fn(obs, info)[0]
        if f.dtype == "image":
            hwc = quantize_images(x).permute(1, 2, 0).cpu().numpy()
            size += len(encode_png(np.ascontiguousarray(hwc), 1))
        else:
            size += 4 * x.numel()
    size += 4 * env.single_action_space.shape[0] + 40  # action + bookkeeping columns
    return size * env.episode_length


def read_recording(root: str | Path) -> dict[str, Any]:
    """A dataset's ``meta/sonogym.json`` (how it was recorded), with a clear error if absent."""
    return read_json(Path(root) / META, "sonogym expert dataset", ("task", "env_kwargs"))
