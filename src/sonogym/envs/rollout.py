"""The one rollout loop: a ``Policy`` acting in a batched env, step by step.

``rollout(env, policy, num_steps)`` yields one ``Step`` per env step; evaluation, the demo and
the dataset recorder consume the same stream and keep what they need. The loop owns the two
things every consumer would otherwise get wrong:

* policy state: ``policy.reset()`` before the first step, ``policy.reset(done)`` for the envs an
  autoreset restarted (SAME_STEP autoreset: the observation returned for them is already the
  new episode's first one);
* what belongs to which episode: ``Step.obs`` / ``Step.info`` are what the action was chosen
  from; ``Step.next_obs`` is the observation the policy sees next (the new episode's for the
  envs in ``Step.done``, whose true last observation is ``Step.final_obs``);
  ``Step.final_info`` holds the metrics of the episodes that ended; ``Step.reset_info`` the
  env's info for the state every env is in after the step (new episodes' start states).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import torch

from sonogym.envs.policy import Policy


@dataclass
class Step:
    """One env step of a rollout (tensors batch-first over the env's ``num_envs``): what the
    action was chosen from, the action, and what ``env.step`` returned."""

    t: int  # step index within this rollout, from 0
    obs: Any  # observation the action was chosen from
    info: dict[str, Any]  # the info the action was chosen from
    action: torch.Tensor  # (N, A)
    next_obs: Any  # what the policy sees next (new episodes' first obs where done)
    reward: torch.Tensor  # (N,)
    terminated: torch.Tensor  # (N,) bool
    truncated: torch.Tensor  # (N,) bool
    next_info: dict[str, Any]  # the info of this transition
    reset_info: dict[str, Any] | None = None  # info of every env's state when any was reset

    @property
    def done(self) -> torch.Tensor:
        """(N,) bool, the episode ended with this step."""
        return self.terminated | self.truncated

    @property
    def ended(self) -> bool:
        """Whether any episode ended with this step."""
        return "final_info" in self.next_info

    @property
    def final_obs(self) -> Any | None:
        """True last observation of the ended episodes (rows where done), else None."""
        return self.next_info.get("final_obs") if self.ended else None

    @property
    def final_info(self) -> dict[str, torch.Tensor] | None:
        """Metrics of the ended episodes, with "env_ids", else None."""
        return self.next_info.get("final_info") if self.ended else None


def rollout(
    env,
    policy: Policy,
    num_steps: int,
    seed: int | None = None,
    reset: bool = True,
    obs: Any = None,
    info: dict[str, Any] | None = None,
) -> Iterator[Step]:
    """Run ``policy`` in ``env`` for ``num_steps`` steps, yielding every ``Step``.

    ``reset=True`` resets the env (with ``seed``) first; ``reset=False`` continues from the
    ``obs`` and ``info`` the caller passes (the env's current state)."""
    if num_steps < 0:
        raise ValueError(f"num_steps must be >= 0, got {num_steps}")
    if reset:
        obs, info = env.reset(seed=seed)
    elif obs is None or info is None:
        raise ValueError("rollout(reset=False) needs the env's current obs and info")
    policy.reset()
    for t in range(num_steps):
        with torch.no_grad():
            action = policy.act(obs, info)
        step = Step(t, obs, info, action, *env.step(action))
        if step.ended:
            step.reset_info = env.current_info()
        yield step
        if step.ended:
            policy.reset(step.done)
            # the new episodes' start states, so the next action sees where they begin
            info = step.reset_info
        else:
            info = step.next_info
        obs = step.next_obs
