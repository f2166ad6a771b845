"""PPO + safety filter (``ppo-sf``; the paper's modified SafeRPlan): the skrl agent, its cost
critic and the test-time filter; on tasks with a cost (surgery).

Training is PPO plus a cost critic Q_c(o_t, a_t) regressed (MSE) on the immediate cost
c_t = 1[p_t+1 unsafe] (``info["cost"]``, the transition a_t caused; no bootstrapping), as the
reference code does. Differences from the reference, on purpose:
the cost critic has its own Adam optimiser (the reference shares one with the policy and
clips only the policy's gradients), and because our cost has no one-step lag, Q_c learns
"this action leads to an unsafe state", not "the current state is unsafe".

The filter acts at test time, where Q_c(o, a) > ``cost_threshold`` (0.5, reference; the
paper's w_i - delta), in one of two modes (``filter_mode``, a run setting that ``sonogym eval
--filter-mode`` overrides):

* ``"zero"``, the paper's and the reference's: the whole action becomes 0 (no motion);
* ``"search"`` (default, ours): the action becomes the nearest of a few variations of it
  (:func:`candidate_actions`) that Q_c predicts safe, and stays where none is or where the
  tracked tip is already outside the safe set (``info["safe"]``: the tracked drill against
  the pre-operative plan, which a navigated system knows; the policy does not observe it).

Why ours: the paper's rule stalls a deterministic policy for good. Zeroing an action leaves
the drill where it is, and there the policy proposes the same action again; a drill that the
critic once let outside the safe set has every later action zeroed, so it stays outside. The
search filter backs off or moves sideways instead, and never holds a drill that is already
outside (there the policy's action is the way back; docs/agents.md, ppo-sf). The filter is
not applied while training (reference).

``CostCritic``: its own surgery encoder (conv over the volume, position and quaternion MLPs,
[512, 256, 128]) and an action MLP 6 -> [128, 128, 64], concatenated -> [256, 128] ELU -> 1.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import torch
import torch.nn.functional as F
from skrl.agents.torch.ppo import PPO, PPO_CFG
from torch import nn

from sonogym.agents.algorithms.ppo_sf.config import check_filter_mode, filter_settings
from sonogym.agents.checkpoint import RLPolicy, load_module, load_policy, newest_checkpoint, run_net
from sonogym.agents.networks import VECTOR_MLP, CostModel, mlp


class CostCritic(CostModel):
    """Q_c(o, a): expected immediate cost of action a in observation o (role "cost_critic")."""

    ROLE = "cost_critic"

    def add_head(self, action_dim: int) -> None:
        self.action_mlp = mlp(action_dim, VECTOR_MLP)
        self.head = nn.Sequential(
            mlp(self.encoder.out_features + VECTOR_MLP[-1], (256, 128)), nn.Linear(128, 1)
        )

    def compute(self, inputs, role: str = ""):
        feats = self.encoder(inputs["observations"])
        act = self.action_mlp(inputs["taken_actions"])
        return self.head(torch.cat([feats, act], dim=-1)), {}

    def q_values(self, observations: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """(K, N) Q_c of K candidate actions (K, N, A) per observation (N, ...), encoding
        each observation once."""
        k, n = actions.shape[:2]
        feats = self.encoder(observations).unsqueeze(0).expand(k, -1, -1)
        act = self.action_mlp(actions.reshape(k * n, -1)).view(k, n, -1)
        return self.head(torch.cat([feats, act], dim=-1)).squeeze(-1)


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
        self.cost_optimizer = self.cost_critic.attach(self, self.cfg.cost_learning_rate)

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


def candidate_actions(actions: torch.Tensor, low: torch.Tensor, high: torch.Tensor) -> torch.Tensor:
    """(K, N, A) candidates for the search filter, K = 2 A + 4, the policy's action first:
    the action, it halved and quartered, each component zeroed in turn, each component negated
    in turn (e.g. backing off along the drill axis while keeping the lateral move), and no
    motion, clipped to the box [low, high]. All are variations of the policy's own action:
    random offsets around it were tried and dropped, because the critic, trained only on the
    policy's own exploration, rates unfamiliar actions wrongly (with them the image run's safe
    ratio fell to 69-74 %, below the zero filter's 78 %)."""
    dim = actions.shape[1]
    eye = torch.eye(dim, device=actions.device, dtype=actions.dtype)
    a = actions.unsqueeze(0)  # (1, N, A)
    zeroed = a * (1 - eye).unsqueeze(1)  # (A, N, A)
    negated = a * (1 - 2 * eye).unsqueeze(1)
    cands = torch.cat([a, 0.5 * a, 0.25 * a, zeroed, negated, torch.zeros_like(a)])
    return torch.maximum(torch.minimum(cands, high), low)


def filter_actions(
    cost_critic: CostCritic,
    observations: torch.Tensor,
    actions: torch.Tensor,
    threshold: float,
    mode: str = "search",
    in_safe_set: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """(filtered actions, (N,) bool mask of rows the filter changed).

    A row whose Q_c(o, a) > ``threshold`` is replaced: ``mode="zero"`` by 0 (the paper's "no
    action is taken"); ``mode="search"`` by the candidate of :func:`candidate_actions` nearest
    to a (Euclidean, each component in units of the box's half-width) among those with
    Q_c <= threshold; where no candidate is predicted safe, the policy's action stays (even no
    motion is predicted to cost 1, i.e. the drill is already outside the safe set, and the
    policy's own action is what brought it back in training; zeroing it there kept drills
    outside for the rest of the episode).

    ``in_safe_set`` ((N,) bool, the env's ``info["safe"]``: the tracked tip against the plan),
    ``mode="search"`` only: rows where it is False keep the policy's action. The filter guards
    the safe set's boundary; once the tip is outside, the policy's action is the way back. The
    critic alone does not always see that: it rated "no motion" safe for a tip already 2.6 mm
    past the entrance plane and 6.9 mm off the axis, and the search filter held that drill
    still there for 540 steps (runs/surg-img-w5-s0, 51,968 steps, IDT episode 74: 5 % safe;
    the unfiltered policy went back into the corridor). The paper's ``"zero"`` rule is kept as
    published. No host reads: selection is tensor ops."""
    check_filter_mode(mode)
    with torch.no_grad():
        if mode == "zero":
            q = cost_critic.q_values(observations, actions.unsqueeze(0))[0]
            unsafe = q > threshold
            return torch.where(unsafe.view(-1, 1), torch.zeros_like(actions), actions), unsafe
        space = cost_critic.action_space
        low = torch.as_tensor(space.low, device=actions.device, dtype=actions.dtype)
        high = torch.as_tensor(space.high, device=actions.device, dtype=actions.dtype)
        cands = candidate_actions(actions, low, high)  # (K, N, A)
        q = cost_critic.q_values(observations, cands)  # (K, N)
        safe = q <= threshold
        dist = (((cands - actions) / ((high - low) / 2)) ** 2).sum(-1)
        nearest_safe = torch.where(safe, dist, torch.full_like(dist, float("inf"))).argmin(0)
        guarded = safe.any(0)
        if in_safe_set is not None:
            guarded = guarded & in_safe_set.to(device=guarded.device, dtype=torch.bool)
        pick = torch.where(guarded, nearest_safe, torch.zeros_like(nearest_safe))  # (N,)
        chosen = cands.gather(0, pick.view(1, -1, 1).expand(1, -1, cands.shape[-1]))[0]
        return chosen, pick != 0


class SafetyFilteredPolicy(RLPolicy):
    """A ``ppo-sf`` run acting deterministically through its safety filter
    (``filter_mode`` "search": an action with Q_c > threshold becomes the nearest candidate
    predicted safe, except where ``info["safe"]`` says the tip is already outside the safe set;
    "zero": it becomes 0)."""

    def __init__(
        self, model, adapter, critic: CostCritic, threshold: float = 0.5,
        filter_mode: str = "search",
    ):  # fmt: skip
        super().__init__(model, adapter)
        self.critic = critic
        self.threshold = threshold
        self.filter_mode = filter_mode

    def act(self, obs, info) -> torch.Tensor:
        x = self.adapter.flatten(obs)
        action = self.model.act({"observations": x}, role="policy")[1]["mean_actions"]
        action, _ = filter_actions(
            self.critic, x, action, self.threshold, self.filter_mode, info.get("safe")
        )
        return action


def load_cost_critic(run: str | Path, checkpoint: str | Path | None = None, device: str = "cpu"):
    """(cost critic in eval mode, filter threshold, filter mode) of a ``ppo-sf`` run."""
    policy, cfg = load_policy(run, checkpoint, device)
    if cfg["algo"] != "ppo-sf":
        raise ValueError(f"{run} is a {cfg['algo']} run; only ppo-sf runs have a cost critic")
    if checkpoint is None:
        checkpoint = newest_checkpoint(Path(run))
    critic = CostCritic(
        cfg["task"], policy.encoder.layout, policy.action_space, device, run_net(cfg)
    )
    load_module(critic, checkpoint, "cost_critic", device)
    critic.eval()
    return critic, *filter_settings(cfg)
