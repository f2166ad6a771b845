"""DAgger warm start: the RL policy's mean imitates a privileged expert before RL begins.

``sonogym train --dagger-expert NAME --dagger-steps N`` (``TrainConfig.dagger``) runs this in
the training process, on the run's own envs, adapter and policy network, before the first
checkpoint: ``agent_0.pt`` holds the warm-started weights and the algorithm (PPO) continues
from them in the same run. The steps:

1. ``iterations`` rounds of ``steps / iterations`` env steps each. Round i (from 0) acts with
   the beta-mixture of the expert and the policy's mean action, beta_i = 1 - i / (iterations
   - 1) (1 for a single round): each env takes the expert's action with probability beta_i,
   else the policy's, every step. The expert sees every visited state (a stateful expert,
   such as navigation's level-counting one, follows whatever trajectory the mixture takes;
   ``sonogym.envs.rollout`` resets it per env at each episode start).
2. Every visited observation, as the policy reads it (``SkrlEnvAdapter.flatten_raw``: pooled
   by ``obs_downsample``, scaled), is stored with the expert's action in a bounded buffer that
   keeps the latest ``buffer`` samples; image entries in [0, 1] are stored as 8-bit
   (round(255 x), at most 1/510 off), the rest as float32.
3. After each round the policy's mean (the shared encoder and the mean head: the actor, on the
   policy's own observation) is fitted to the expert's actions by mean squared error in action
   units: ``updates`` Adam steps at ``learning_rate`` on mini-batches of ``batch_size`` drawn
   uniformly from the buffer. The log-std and the value head are left as they are (the value
   head reads the trained encoder's features from then on and learns in RL).

The envs then restart from the run's seed, as an RL run without a warm start begins.
``config.json`` records the settings (``dagger``) and what came of them (``dagger_result``:
beta per round, samples seen and kept, the buffer's MSE before the first fit and after each
round, CPU and wall seconds; these count in the run's ``times.json``).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from sonogym.agents.adapter import IMAGE_KEYS, SkrlEnvAdapter
from sonogym.envs.base import check_number_fields
from sonogym.envs.policy import ExpertPolicy
from sonogym.envs.registry import get_task
from sonogym.envs.rollout import rollout

#: the task's own expert (``TaskSpec.expert``); other names are its ``TaskSpec.experts``
TASK_EXPERT = "expert"


@dataclass(frozen=True)
class DaggerConfig:
    """A DAgger warm start's settings (units: env steps per env; samples; action units)."""

    expert: str  # "expert" (the task's) or one of the task's further experts ("level-counting")
    steps: int  # env steps per env of the warm start, over all rounds
    iterations: int = 8  # rounds; beta falls linearly from 1 to 0 over them
    buffer: int = 16_384  # samples kept (the latest); bounds the warm start's memory
    updates: int = 250  # mini-batch gradient steps per round
    batch_size: int = 256  # samples per mini-batch
    learning_rate: float = 3e-4  # Adam, per optimiser step

    def __post_init__(self) -> None:
        check_number_fields(self)
        for name in ("steps", "iterations", "buffer", "updates", "batch_size"):
            if getattr(self, name) < 1:
                raise ValueError(f"dagger {name} must be >= 1, got {getattr(self, name)}")
        if self.iterations > self.steps:
            raise ValueError(
                f"dagger needs at least one step per round: {self.steps} steps for "
                f"{self.iterations} rounds; pass more --dagger-steps"
            )
        if not self.learning_rate > 0:
            raise ValueError(f"dagger learning_rate must be > 0, got {self.learning_rate}")

    def betas(self) -> list[float]:
        """beta of each round: 1 -> 0 linearly (a single round: 1, behaviour cloning)."""
        k = self.iterations
        return [1.0] if k == 1 else [1.0 - i / (k - 1) for i in range(k)]

    def round_ends(self) -> list[int]:
        """The env step (per env, from 1) at which each round ends and the policy is fitted."""
        return [round(self.steps * (i + 1) / self.iterations) for i in range(self.iterations)]

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def expert_names(task: str) -> tuple[str, ...]:
    """The experts a warm start on ``task`` may imitate."""
    return (TASK_EXPERT, *get_task(task).experts)


def check_expert(task: str, name: str) -> None:
    """Refuse an expert ``task`` does not have, naming the ones it has."""
    if name not in expert_names(task):
        raise ValueError(
            f"--dagger-expert {name!r}: {task} has no such expert; choose from "
            f"{list(expert_names(task))}"
        )


def make_expert(task: str, name: str, env):
    """The ``Policy`` of expert ``name`` on ``env`` (an env of ``task``)."""
    check_expert(task, name)
    spec = get_task(task)
    if name == TASK_EXPERT:
        return ExpertPolicy(env, spec.expert)
    return spec.expert_factory(name)(env)


class SampleBuffer:
    """The latest ``capacity`` (flat observation, expert action) pairs; image entries bounded
    to [0, 1] in 8 bits, the rest in float32 (module docstring)."""

    def __init__(self, capacity: int, adapter: SkrlEnvAdapter, action_dim: int) -> None:
        layout, device = adapter.layout, adapter.device
        quantized = np.zeros(layout.size, bool)
        start = 0
        for key, shape, size in zip(layout.keys, layout.shapes, layout.sizes, strict=True):
            if _unit_image(adapter, key, shape):
                quantized[start : start + size] = True
            start += size
        self.q_cols = torch.from_numpy(np.flatnonzero(quantized)).to(device)
        self.f_cols = torch.from_numpy(np.flatnonzero(~quantized)).to(device)
        self.size_, self.capacity, self.next = layout.size, int(capacity), 0
        self.count = 0  # samples currently held
        self.seen = 0  # samples ever added
        self.q = torch.zeros(capacity, len(self.q_cols), dtype=torch.uint8, device=device)
        self.f = torch.zeros(capacity, len(self.f_cols), device=device)
        self.actions = torch.zeros(capacity, action_dim, device=device)

    @staticmethod
    def bytes_per_sample(adapter: SkrlEnvAdapter, action_dim: int) -> int:
        layout, n = adapter.layout, 0
        for key, shape, size in zip(layout.keys, layout.shapes, layout.sizes, strict=True):
            n += size if _unit_image(adapter, key, shape) else 4 * size
        return n + 4 * action_dim

    def add(self, flat: torch.Tensor, actions: torch.Tensor) -> None:
        n = flat.shape[0]
        idx = (self.next + torch.arange(n, device=flat.device)) % self.capacity
        self.q[idx] = (flat[:, self.q_cols].clamp(0, 1) * 255).round().to(torch.uint8)
        self.f[idx] = flat[:, self.f_cols]
        self.actions[idx] = actions.to(self.actions.dtype)
        self.next = (self.next + n) % self.capacity
        self.count = min(self.capacity, self.count + n)
        self.seen += n

    def get(self, idx: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(flat observations (B, D) float32, expert actions (B, A)) of rows ``idx``."""
        flat = torch.empty(len(idx), self.size_, device=self.f.device)
        flat[:, self.q_cols] = self.q[idx].float() / 255
        flat[:, self.f_cols] = self.f[idx]
        return flat, self.actions[idx]


def _unit_image(adapter: SkrlEnvAdapter, key: str, shape: tuple[int, ...]) -> bool:
    """Whether entry ``key`` is an image bounded to [0, 1] and unscaled (stored in 8 bits)."""
    space = adapter.unwrapped.single_observation_space
    entry = space if key == "_" else space.spaces[key]
    image = len(shape) >= 2 and (key == "_" or key in IMAGE_KEYS)
    bounded = bool(np.all(entry.low == 0) and np.all(entry.high == 1))
    return image and bounded and key not in adapter.obs_scales


class _Mixture:
    """The beta-mixture acting in the envs; keeps what each step saw for the buffer."""

    def __init__(self, expert, adapter: SkrlEnvAdapter, mean: Callable, seed: int) -> None:
        self.expert, self.adapter, self.mean = expert, adapter, mean
        self.beta = 1.0
        self.gen = torch.Generator(device="cpu").manual_seed(seed)
        self.flat: torch.Tensor | None = None  # raw flat observations of the last act
        self.label: torch.Tensor | None = None  # the expert's actions there

    def reset(self, env_mask: torch.Tensor | None = None) -> None:
        self.expert.reset(env_mask)

    def act(self, obs, info) -> torch.Tensor:
        self.label = self.expert.act(obs, info).float()
        self.flat = self.adapter.flatten_raw(obs)
        n = self.label.shape[0]
        pick = (torch.rand(n, generator=self.gen) < self.beta).to(self.label.device)
        if bool(pick.all()):
            return self.label
        x = self.adapter.standardize(self.flat.clone(), self.adapter.update_stats)
        return torch.where(pick.unsqueeze(-1), self.label, self.mean(x))


def policy_mean(model) -> Callable[[torch.Tensor], torch.Tensor]:
    """The policy's mean action on flat (standardised) observations."""
    return lambda x: model.compute({"observations": x}, role="policy")[0]


def run_dagger(
    cfg: DaggerConfig, task: str, adapter: SkrlEnvAdapter, model, seed: int,
    log: Callable[[str], None],
) -> dict[str, Any]:  # fmt: skip
    """Warm-start ``model``'s mean on ``adapter``'s envs (module docstring); the result that
    ``config.json`` records as ``dagger_result``."""
    from sonogym.memory import check_fits, free_memory

    env = adapter.unwrapped
    action_dim = int(adapter.action_space.shape[0])
    check_fits(
        cfg.buffer * SampleBuffer.bytes_per_sample(adapter, action_dim), free_memory(env.device),
        f"the DAgger buffer of {cfg.buffer} samples", "memory",
        "use a smaller DaggerConfig.buffer or a larger --obs-downsample",
    )  # fmt: skip
    cpu0, wall0 = time.process_time(), time.time()
    buffer = SampleBuffer(cfg.buffer, adapter, action_dim)
    mean = policy_mean(model)
    mixture = _Mixture(make_expert(task, cfg.expert, env), adapter, mean, seed)
    optimizer = torch.optim.Adam(model.parameters(), lr=cfg.learning_rate)
    gen = torch.Generator(device="cpu").manual_seed(seed + 1)
    betas, ends = cfg.betas(), cfg.round_ends()
    losses: list[float] = []
    before = None
    k = 0
    mixture.beta = betas[0]
    for step in rollout(env, mixture, cfg.steps, seed=seed):
        buffer.add(mixture.flat, mixture.label)
        if step.t + 1 != ends[k]:
            continue
        if before is None:
            before = buffer_mse(model, adapter, buffer)
        _fit(model, adapter, buffer, optimizer, cfg, gen)
        losses.append(buffer_mse(model, adapter, buffer))
        log(f"dagger round {k + 1}/{cfg.iterations}: beta {betas[k]:.2f}, "
            f"{buffer.count} samples, MSE {losses[-1]:.4f}")  # fmt: skip
        k += 1
        if k < len(betas):
            mixture.beta = betas[k]
    adapter.restart(update_stats=adapter.update_stats)  # the run begins from its seed
    return {
        "beta": [round(b, 6) for b in betas],
        "samples_seen": buffer.seen,
        "samples_kept": buffer.count,
        "mse_before": before,
        "mse": losses,
        "final_mse": losses[-1],
        "cpu_s": round(time.process_time() - cpu0, 1),
        "wall_s": round(time.time() - wall0, 1),
    }


def _fit(model, adapter, buffer: SampleBuffer, optimizer, cfg: DaggerConfig, gen) -> None:
    """``cfg.updates`` mini-batch MSE steps on the buffer."""
    batch = min(cfg.batch_size, buffer.count)
    mean = policy_mean(model)
    for _ in range(cfg.updates):
        idx = torch.randint(buffer.count, (batch,), generator=gen).to(buffer.f.device)
        flat, target = buffer.get(idx)
        loss = (mean(adapter.standardize(flat)) - target).pow(2).mean()
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
    optimizer.zero_grad(set_to_none=True)


@torch.no_grad()
def buffer_mse(model, adapter, buffer: SampleBuffer, chunk: int = 1024) -> float:
    """The policy mean's MSE (action units) against the expert over the whole buffer."""
    mean, total = policy_mean(model), 0.0
    for start in range(0, buffer.count, chunk):
        idx = torch.arange(start, min(start + chunk, buffer.count), device=buffer.f.device)
        flat, target = buffer.get(idx)
        total += float((mean(adapter.standardize(flat)) - target).pow(2).sum())
    return total / (buffer.count * buffer.actions.shape[1])
