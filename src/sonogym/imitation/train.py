"""Train a registered IL policy (ACT, Diffusion Policy, ...: ``policies.registry``) on a
LeRobotDataset v3.0 folder (``train_il``).

One input, ``ILTrainConfig``. The run folder layout and checkpoint format: ``run.py``.
Samples: random frames of the dataset (with replacement across epochs, reshuffled each epoch)
with the policy's observation history and action chunk (``delta_indices``), leaving the
policy's ``drop_n_last_frames`` of each episode out (Diffusion Policy: the last
``horizon - n_action_steps - n_obs_steps + 1``, LeRobot's sampler). Optimiser, learning-rate
schedule, gradient clip and normalisation come from the policy (LeRobot's choices: ACT AdamW
at a constant rate, DP Adam with linear warm-up then cosine decay to 0 over ``steps``); the
training step itself is the same for every policy.

Determinism: one seed drives the model's initialisation, the sample order and the model's own
noise (VAE sampling, diffusion noise, random crops). ``resume=True`` restores weights,
optimiser, schedule and generators from the newest checkpoint; the data order after a resume
differs from an uninterrupted run's.
"""

from __future__ import annotations

import dataclasses
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from sonogym.imitation import run as runio
from sonogym.imitation.lerobot_format import read_info
from sonogym.imitation.policies.registry import get_policy, make_config, policy_names
from sonogym.imitation.processor import PolicyFeatures, stats_subset
from sonogym.imitation.reader import LeRobotFrames, load_stats
from sonogym.progress import progress_bar
from sonogym.runs import RunFolder, TrainingInterrupted, deleted_message, prepare_output


@dataclass(frozen=True)
class ILTrainConfig:
    """Everything ``train_il`` needs.

    data: LeRobotDataset v3.0 folder.
    out: run folder (refused if it exists, unless ``resume`` or ``force``).
    policy: a registered policy's name ("act", "diffusion", ...: ``policies.registry``).
    policy_config: that policy's config (``ACTConfig``, ``DiffusionConfig``, ...); None: the
        ``size`` of ``policy``.
    size: the policy's model size, "cpu" or "paper" (used when ``policy_config`` is None).
    steps: optimiser steps in total, resumed ones included (>= 1).
    batch_size: samples per step (the reference: 8).
    seed: seed of initialisation, sample order and the model's noise.
    device: torch device of the model and batches ("cpu", "cuda", ...).
    resume: continue from the newest checkpoint in ``out``.
    force: delete an existing run folder ``out`` first.
    save_every: steps between checkpoints (a final one is always written).
    save_minutes: a checkpoint at least this often (minutes of training) between those, so a
        killed run (SIGKILL, a lost machine) loses at most that much; each such checkpoint
        replaces the previous such one of this call; 0: none.
    log_every: steps between TensorBoard scalars.
    num_workers: DataLoader worker processes (0: load in the training process).
    image_cache: the reader's image cache, "bytes" or "decoded" (see ``LeRobotFrames``).
    episodes: episode indices to train on (None: all).
    progress: show the progress (``sonogym.progress``: a bar on a terminal, a line every few
        percent in a log).
    """

    data: str
    out: str
    policy: str = "act"
    policy_config: Any = None
    size: str = "cpu"
    steps: int = 10_000
    batch_size: int = 8
    seed: int = 1000
    device: str = "cpu"
    resume: bool = False
    force: bool = False
    save_every: int = 5_000
    save_minutes: float = 5.0
    log_every: int = 100
    num_workers: int = 0
    image_cache: str = "bytes"
    episodes: tuple[int, ...] | None = None
    progress: bool = True

    def __post_init__(self) -> None:
        if self.policy not in policy_names():
            raise ValueError(f"policy {self.policy!r} unknown; choose one of {policy_names()}")
        config_cls = get_policy(self.policy).config_cls
        if self.policy_config is not None and not isinstance(self.policy_config, config_cls):
            raise ValueError(
                f"policy {self.policy!r} with a {type(self.policy_config).__name__}: they differ"
            )
        if self.steps < 1 or self.batch_size < 1 or self.save_every < 1 or self.log_every < 1:
            raise ValueError("steps, batch_size, save_every and log_every must be >= 1")
        if not self.save_minutes >= 0:
            raise ValueError(f"save_minutes must be >= 0 (0: none), got {self.save_minutes}")
        if self.resume and self.force:
            raise ValueError("resume and force exclude each other")

    def resolved_policy_config(self):
        return self.policy_config or make_config(self.policy, self.size)


def parse_image_size(text: str) -> tuple[int, int]:
    """``--image-size`` text "HxW" (pixels, e.g. "100x75") -> (H, W)."""
    h, sep, w = text.lower().partition("x")
    if not (sep and h.isdigit() and w.isdigit() and int(h) > 0 and int(w) > 0):
        raise ValueError(f"--image-size takes HxW in pixels, e.g. 100x75; got {text!r}")
    return int(h), int(w)


def il_train_settings(
    policy: str,
    old: dict[str, Any] | None = None,
    *,
    size: str | None = None,
    image_size: str | None = None,
    steps: int | None = None,
    batch_size: int | None = None,
    seed: int | None = None,
) -> dict[str, Any]:
    """The ``ILTrainConfig`` fields ``policy``, ``size``, ``policy_config``, ``steps``,
    ``batch_size`` and ``seed`` that ``sonogym il-train``'s options resolve to (None: not
    given).

    ``old``: the config.json of the run being resumed (None: a new run). What is left out
    continues as that run was trained: its seed, batch size, steps and, unless ``size`` or
    ``image_size`` is given or the policy differs, its policy config. A new run takes the
    ``cpu`` size, 10 000 steps, batches of 8 and seed 1000. ``image_size``: "HxW" in pixels.
    """
    if old is not None:
        seed = old["seed"] if seed is None else seed
        batch_size = old["train"]["batch_size"] if batch_size is None else batch_size
        steps = old["train"]["steps"] if steps is None else steps
    overrides = {} if image_size is None else {"image_size": parse_image_size(image_size)}
    if old is not None and not (overrides or size is not None) and old["policy"] == policy:
        policy_config = get_policy(policy).config_cls.from_dict(old["policy_config"])
    else:
        policy_config = make_config(policy, size or "cpu", **overrides) if overrides else None
    return {
        "policy": policy,
        "size": size or "cpu",
        "policy_config": policy_config,
        "steps": steps or 10_000,
        "batch_size": batch_size or 8,
        "seed": 1000 if seed is None else seed,
    }


@dataclass(frozen=True)
class ILTrainResult:
    run: Path
    steps: int  # optimiser steps done in total
    loss: float  # mean training loss over the last log interval
    seconds: float  # wall time of this call's training loop
    history: tuple[tuple[int, float], ...]  # (step, mean loss of the interval) per log


def _recording(data: Path) -> dict:
    """How a sonogym-recorded dataset was recorded (``meta/sonogym.json``); {} for others."""
    from sonogym.imitation.record import META, read_recording

    return read_recording(data) if (data / META).is_file() else {}


def _resume_state(cfg: ILTrainConfig):
    """On resume the run's config and newest readable checkpoint's state (read before anything
    is written); (None, None) for a new run."""
    if not cfg.resume:
        return None, None
    old = runio.read_run_config(cfg.out)
    found = RunFolder(cfg.out, runio.IL_RUN).newest_readable_checkpoint(cfg.device)
    return old, None if found is None else found.state


def _resume_conflicts(old: dict, new: dict) -> list[str]:
    """What a resumed run would change that defines the run, by name (run's value after)."""
    out = []
    for key in ("policy", "seed"):
        if old.get(key) != new.get(key):
            out.append(f"{key} {new.get(key)!r} (run: {old.get(key)!r})")
    for key in ("batch_size", "episodes"):
        if old["train"].get(key) != new["train"].get(key):
            out.append(f"{key} {new['train'].get(key)!r} (run: {old['train'].get(key)!r})")
    if old.get("dataset", {}).get("root") != new["dataset"]["root"]:
        out.append(f"data {new['dataset']['root']!r} (run: {old.get('dataset', {}).get('root')!r})")
    pc_old, pc_new = old["policy_config"], new["policy_config"]
    for k in sorted(set(pc_old) | set(pc_new)):
        if pc_old.get(k) != pc_new.get(k):
            out.append(f"policy_config.{k} {pc_new.get(k)!r} (run: {pc_old.get(k)!r})")
    if old["features"] != new["features"]:
        out.append("the dataset's features")
    return out


def train_il(cfg: ILTrainConfig) -> ILTrainResult:
    """Train (or resume) an IL policy; see the module doc. Returns the run folder and totals.
    The run folder is locked while it trains (``sonogym.runs.prepare_output``)."""
    pcfg = cfg.resolved_policy_config()
    # the dataset is read and checked (its statistics, the recorded task's features, every
    # numeric value) before the run folder is touched
    data = Path(cfg.data).resolve()
    info = read_info(data)
    stats = load_stats(data)
    features = PolicyFeatures.from_info(info["features"])
    recording = _recording(data)
    if recording.get("task"):
        from sonogym.imitation.record import check_task_features

        check_task_features(recording["task"], features, f"{data} (meta/sonogym.json)")
    ds = LeRobotFrames(
        data,
        delta_indices=pcfg.delta_indices(features),
        episodes=None if cfg.episodes is None else list(cfg.episodes),
        drop_n_last_frames=pcfg.drop_n_last_frames,
        image_cache=cfg.image_cache,
    )
    if len(ds) == 0:
        raise ValueError(f"{data}: no training samples (episodes too short for the policy?)")
    with prepare_output(cfg.out, cfg.resume, cfg.force, kind="il-run") as folder:
        if folder.deleted:
            print(deleted_message(cfg.out, folder.deleted))
        return _train(cfg, pcfg, _Dataset(data, info, stats, features, recording, ds))


@dataclasses.dataclass(frozen=True)
class _Dataset:
    """The checked dataset a run trains on."""

    root: Path
    info: dict
    stats: dict
    features: PolicyFeatures
    recording: dict
    frames: LeRobotFrames


@dataclasses.dataclass
class _Learner:
    """What one IL run trains and saves: the model, its optimiser and schedule, and the two
    random streams (the model's noise and the loader's order)."""

    model: torch.nn.Module
    opt: torch.optim.Optimizer
    sched: torch.optim.lr_scheduler.LRScheduler
    gen: torch.Generator
    loader_gen: torch.Generator

    def state(self, step: int) -> dict:
        return {
            "model": self.model.state_dict(),
            "optimizer": self.opt.state_dict(),
            "scheduler": self.sched.state_dict(),
            "step": step,
            "rng": {"model": self.gen.get_state(), "loader": self.loader_gen.get_state()},
        }

    def load(self, state: dict) -> int:
        """Restore a checkpoint's state; returns its step."""
        self.model.load_state_dict(state["model"])
        self.opt.load_state_dict(state["optimizer"])
        self.sched.load_state_dict(state["scheduler"])
        self.gen.set_state(state["rng"]["model"].cpu())
        self.loader_gen.set_state(state["rng"]["loader"].cpu())
        return int(state["step"])


def _learner(cfg: ILTrainConfig, pcfg, spec, dataset: _Dataset, dev: torch.device) -> _Learner:
    """The seeded model (its initial weights from ``cfg.seed``), optimiser, schedule and
    random streams, in the order that fixes them."""
    torch.manual_seed(cfg.seed)
    model = spec.model_cls(pcfg, dataset.features, dataset.stats).to(dev)
    model.train()
    opt = model.optimizer()
    sched = torch.optim.lr_scheduler.LambdaLR(opt, model.lr_lambda(cfg.steps))
    gen = torch.Generator(device=dev).manual_seed(cfg.seed + 1)
    loader_gen = torch.Generator().manual_seed(cfg.seed + 2)
    return _Learner(model, opt, sched, gen, loader_gen)


def _run_config(cfg: ILTrainConfig, pcfg, spec, dataset: _Dataset, model) -> dict:
    """The run's ``config.json``, in the form the file holds (tuples as lists)."""
    info, recording = dataset.info, dataset.recording
    run_cfg = {
        # what evaluation needs without the dataset: the task and the env it imaged
        "task": recording.get("task"),
        "algo": spec.algo,
        "seed": cfg.seed,
        "env_kwargs": recording.get("eval_env_kwargs", {}),
        # the dataset's; None for a dataset recorded elsewhere or by an older sonogym
        "identity": recording.get("identity"),
        "policy": cfg.policy,
        "policy_config": pcfg.to_dict(),
        "train": {k: v for k, v in dataclasses.asdict(cfg).items() if k != "policy_config"},
        "dataset": {
            "root": str(dataset.root),
            "codebase_version": info["codebase_version"],
            "fps": info["fps"],
            "total_episodes": info["total_episodes"],
            "total_frames": info["total_frames"],
            "features": info["features"],
        },
        "features": dataset.features.to_dict(),
        "normalization": dict(model.normalizer.modes),
        "stats": stats_subset(dataset.stats, dataset.features.keys),
        "versions": {"torch": torch.__version__},
    }
    return json.loads(json.dumps(run_cfg))


def _check_resume(cfg: ILTrainConfig, old: dict | None, state: dict | None, run_cfg: dict) -> None:
    """Refuse to resume a run with other options, or to a total below its steps so far."""
    if old is None:
        return
    conflicts = _resume_conflicts(old, run_cfg)
    if conflicts:
        raise ValueError(
            f"{cfg.out} cannot be resumed with {', '.join(conflicts)}: leave those options out "
            "(the run's are used) or train into a new folder"
        )
    if state is not None and int(state["step"]) > cfg.steps:
        raise ValueError(
            f"{cfg.out} has trained {int(state['step'])} steps already; --steps is the total, "
            f"so give more than that to continue (got {cfg.steps})"
        )


def _batches(cfg: ILTrainConfig, ds, loader_gen: torch.Generator, dev: torch.device):
    """Endless shuffled batches of ``ds`` in the order ``loader_gen`` draws."""
    loader = torch.utils.data.DataLoader(
        ds,
        batch_size=cfg.batch_size,
        shuffle=True,
        drop_last=len(ds) >= cfg.batch_size,
        num_workers=cfg.num_workers,
        generator=loader_gen,
        pin_memory=dev.type == "cuda",
        persistent_workers=cfg.num_workers > 0,
    )
    while True:
        yield from loader


def _train(cfg: ILTrainConfig, pcfg, dataset: _Dataset) -> ILTrainResult:
    out = Path(cfg.out)
    old, state = _resume_state(cfg)
    dev = torch.device(cfg.device)
    spec = get_policy(cfg.policy)
    learner = _learner(cfg, pcfg, spec, dataset, dev)
    run_cfg = _run_config(cfg, pcfg, spec, dataset, learner.model)
    _check_resume(cfg, old, state, run_cfg)
    start = learner.load(state) if state is not None else 0
    runio.write_run_config(out, run_cfg)
    batches = _batches(cfg, dataset.frames, learner.loader_gen, dev)
    return _loop(cfg, pcfg, learner, batches, start, dev)


def _loop(cfg: ILTrainConfig, pcfg, learner: _Learner, batches, start: int, dev) -> ILTrainResult:
    """Train from step ``start`` to ``cfg.steps``: log every ``log_every`` steps, save every
    ``save_every`` (and every ``save_minutes``), save and stop cleanly on bad data or Ctrl-C."""
    from torch.utils.tensorboard import SummaryWriter

    out = Path(cfg.out)
    model, opt, sched, gen = learner.model, learner.opt, learner.sched, learner.gen
    tb = SummaryWriter(str(out / "tb"))
    sums: dict[str, float] = {}
    n_sum = 0
    last_loss = float("nan")
    history: list[tuple[int, float]] = []
    t0 = time.perf_counter()
    bar = progress_bar(cfg.steps, f"il-train {cfg.policy}", initial=start, unit="step",
                       enabled=cfg.progress)  # fmt: skip
    step = start
    resume_hint = (
        f"sonogym il-train --policy {cfg.policy} --data {cfg.data} --out {out} --steps "
        f"{cfg.steps} --resume"
    )
    saved_at = time.monotonic()
    timed: Path | None = None  # the last checkpoint written for time, not on the step grid

    def save(step: int) -> Path:
        return runio.save_checkpoint(out, step, learner.state(step))

    try:
        while step < cfg.steps:
            try:
                raw = next(batches)
            except Exception:  # bad data (an undecodable frame): keep what was learnt
                path = save(step)
                print(f"stopped at step {step} of {cfg.steps} by the error below; saved {path}. "
                      f"Fix the data, then resume with: {resume_hint}")  # fmt: skip
                raise
            batch = {k: v.to(dev, non_blocking=True) for k, v in raw.items()}
            loss, logs = model.compute_loss(batch, gen)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            grad = torch.nn.utils.clip_grad_norm_(model.parameters(), pcfg.grad_clip_norm)
            opt.step()
            sched.step()
            step += 1
            logs = {"loss": float(loss.detach()), "grad_norm": float(grad), **logs}
            for k, v in logs.items():
                sums[k] = sums.get(k, 0.0) + v
            n_sum += 1
            if step % cfg.log_every == 0 or step == cfg.steps:
                means = {k: v / n_sum for k, v in sums.items()}
                for k, v in means.items():
                    tb.add_scalar(f"train/{k}", v, step)
                tb.add_scalar("train/lr", sched.get_last_lr()[0], step)
                last_loss = means["loss"]
                history.append((step, last_loss))
                bar.set_postfix(loss=f"{last_loss:.4f}")
                sums, n_sum = {}, 0
            if step % cfg.save_every == 0 or step == cfg.steps:
                save(step)
                saved_at = time.monotonic()
            elif cfg.save_minutes and time.monotonic() - saved_at >= 60 * cfg.save_minutes:
                path = save(step)
                if timed is not None:  # one time-based checkpoint is enough to resume from
                    timed.unlink(missing_ok=True)
                timed, saved_at = path, time.monotonic()
            bar.update(1)
    except KeyboardInterrupt:
        bar.close()
        path = save(step)
        msg = f"interrupted after {step} of {cfg.steps} steps; saved {path}. Resume with: "
        msg += resume_hint
        print(msg)
        raise TrainingInterrupted(msg) from None
    finally:
        bar.close()
        tb.close()
    return ILTrainResult(out, step, last_loss, time.perf_counter() - t0, tuple(history))
