"""PPO + safety filter (``ppo-sf``; the paper's modified SafeRPlan), surgery only.

Training is PPO plus a cost critic Q_c(o_t, a_t) regressed (MSE) on the immediate cost
c_t = 1[p_t+1 unsafe] (``info["cost"]``, the transition a_t caused; no bootstrapping), as the
reference does (reference_implementation.md §7.3). Differences from the reference, on purpose:
the cost critic has its own Adam optimiser (the reference shares one with the policy and
clips only the policy's gradients), and because our cost has no one-step lag, Q_c learns
"this action leads to an unsafe state", not "the current state is unsafe".

The filter acts at test time: where Q_c(o, a) > ``cost_threshold`` (0.5, reference; the
paper's w_i - delta) the whole action is replaced by 0 (no motion). It is not applied while
training (reference).

``CostCritic``: its own surgery encoder (conv over the volume, position and quaternion MLPs,
[512, 256, 128]) and an action MLP 6 -> [128, 128, 64], concatenated -> [256, 128] ELU -> 1.
"""

from __future__ import annotations

import dataclasses

import gymnasium as gym
import torch
import torch.nn.functional as F
from skrl.agents.torch.ppo import PPO, PPO_CFG
from skrl.models.torch import DeterministicMixin, Model
from torch import nn

from sonogym.agents.adapter import ObsLayout
from sonogym.agents.networks import VECTOR_MLP, Encoder, init_flat_model, mlp


class CostCritic(DeterministicMixin, Model):
    """Q_c(o, a): expected immediate cost of action a in observation o (role "cost_critic")."""

    def __init__(
        self,
        task: str,
        layout: ObsLayout,
        action_space: gym.spaces.Box,
        device: str | torch.device | None = None,
        net: str = "paper",
    ) -> None:
        init_flat_model(self, layout, action_space, device)
        DeterministicMixin.__init__(self, clip_actions=False, role="cost_critic")
        self.encoder = Encoder(task, layout, net)
        self.action_mlp = mlp(int(action_space.shape[0]), VECTOR_MLP)
        self.head = nn.Sequential(
            mlp(self.encoder.out_features + VECTOR_MLP[-1], (256, 128)), nn.Linear(128, 1)
        )
        self.to(self.device)

    def compute(self, inputs, role: str = ""):
        feats = self.encoder(inputs["observations"])
        act = self.action_mlp(inputs["taken_actions"])
        return self.head(torch.cat([feats, act], dim=-1)), {}


@dataclasses.dataclass(kw_only=True)
class PPO_SF_CFG(PPO_CFG):
    """PPO settings plus the cost critic's."""

    cost_learning_rate: float = 1e-4  # Adam, per optimiser step
    cost_threshold: float = 0.5  # filter threshold on Q_c (reference)


class PPOSafetyFilter(PPO):
    """skrl PPO with a cost critic (``models["cost_critic"]``) and a test-time action filter."""

    def __init__(self, *, models, cfg: PPO_SF_CFG, **kwargs) -> None:
        super().__init__(models=models, cfg=cfg, **kwargs)
        self.cost_critic = models["cost_critic"]
        self.cost_optimizer = torch.optim.Adam(
            self.cost_critic.parameters(), lr=self.cfg.cost_learning_rate
        )
        self.checkpoint_modules["cost_critic"] = self.cost_critic
        self.checkpoint_modules["cost_optimizer"] = self.cost_optimizer

    def init(self, *, trainer_cfg=None) -> None:
        super().init(trainer_cfg=trainer_cfg)
        if self.memory is not None:
            self.memory.create_tensor(name="costs", size=1, dtype=torch.float32)

    def record_transition(self, *, infos, **kwargs) -> None:
        if self.training:
            if "cost" not in infos:
                raise KeyError("ppo-sf needs info['cost'] from the env (the surgery task has it)")
            # the row PPO's add_samples is about to fill (it advances memory_index after)
            row = self.memory.tensors["costs"][self.memory.memory_index]
            row.copy_(infos["cost"].to(torch.float32).view(-1, 1))
        super().record_transition(infos=infos, **kwargs)

    def update(self, *, timestep: int, timesteps: int) -> None:
        super().update(timestep=timestep, timesteps=timesteps)
        total, count = 0.0, 0
        for _ in range(self.cfg.learning_epochs):
            for obs, actions, costs in self.memory.sample(
                names=["observations", "actions", "costs"],
                batch_size=len(self.memory),
                mini_batches=self.cfg.mini_batches,
            ):
                inputs = {
                    "observations": self._observation_preprocessor(obs),
                    "taken_actions": actions,
                }
                pred, _ = self.cost_critic.act(inputs, role="cost_critic")
                loss = F.mse_loss(pred, costs)
                self.cost_optimizer.zero_grad()
                loss.backward()
                if self.cfg.grad_norm_clip > 0:
                    nn.utils.clip_grad_norm_(self.cost_critic.parameters(), self.cfg.grad_norm_clip)
                self.cost_optimizer.step()
                total, count = total + loss.item(), count + 1
        self.track_data("Loss / Cost critic loss", total / max(count, 1))


def filter_actions(
    cost_critic: CostCritic, observations: torch.Tensor, actions: torch.Tensor, threshold: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """(actions with rows whose Q_c > threshold set to 0, (N,) bool mask of filtered rows)."""
    with torch.no_grad():
        q, _ = cost_critic.act(
            {"observations": observations, "taken_actions": actions}, role="cost_critic"
        )
    unsafe = q.view(-1) > threshold
    return torch.where(unsafe.view(-1, 1), torch.zeros_like(actions), actions), unsafe
