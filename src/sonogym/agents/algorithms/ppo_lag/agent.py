"""PPO-Lagrangian (``ppo-lag``), on tasks with a cost (surgery): PPO with a cost value network
and a PID multiplier.

Per update (as the reference code does; Stooke et al. 2020):

* cost advantages and returns by GAE on c_t = ``info["cost"]`` (same gamma, lambda; time-limit
  bootstrapping as for rewards) with a separate cost value network V_c;
* lambda from a PID on e = J_c - ``cost_limit``, J_c = the rollout's mean discounted cost
  return (the cost-to-go estimate the reference uses): lambda = max(0, Kp e + Ki I + Kd
  max(0, J_c - J_c_prev)), I = max(0, I + e); gains (0.05, 0.0005, 0.1) (reference);
* policy loss = (L_PPO + lambda mean(ratio A_c)) / (1 + lambda) (reference), value loss as PPO,
  cost value loss = MSE(V_c, cost returns), V_c with its own Adam optimiser.

``cost_limit`` default 5 (discounted cost units: with gamma = 0.99 about 5 % of the next ~100
steps unsafe). The reference's 200 can never bind: c in {0, 1} bounds the discounted cost
return by 1 / (1 - gamma) = 100, so its lambda stays 0 and PPO-L is plain PPO.
"""

from __future__ import annotations

import dataclasses
import itertools

import torch
import torch.nn.functional as F
from skrl.agents.torch.ppo import PPO, PPO_CFG
from skrl.agents.torch.ppo.ppo import compute_gae
from skrl.resources.schedulers.torch import KLAdaptiveLR
from torch import nn

from sonogym.agents.networks import CostModel


class CostValue(CostModel):
    """V_c(o): expected discounted cost-to-go (role "cost_value"); its own task encoder."""

    ROLE = "cost_value"

    def add_head(self, action_dim: int) -> None:
        self.head = nn.Linear(self.encoder.out_features, 1)

    def compute(self, inputs, role: str = ""):
        return self.head(self.encoder(inputs["observations"])), {}


class PIDLagrangian(nn.Module):
    """lambda >= 0 from a PID on the constraint violation; state in buffers (checkpointed)."""

    def __init__(self, kp: float, ki: float, kd: float) -> None:
        super().__init__()
        self.kp, self.ki, self.kd = kp, ki, kd
        self.register_buffer("integral", torch.zeros(()))
        self.register_buffer("previous", torch.zeros(()))
        self.register_buffer("value", torch.zeros(()))
        self.register_buffer("started", torch.zeros((), dtype=torch.bool))

    def update(self, cost: float, limit: float) -> float:
        """New lambda for the measured cost J_c and the limit (same units); the first call has
        no derivative term (no previous measurement)."""
        e = cost - limit
        self.integral.copy_(torch.clamp(self.integral + e, min=0.0))
        rise = max(0.0, cost - float(self.previous)) if bool(self.started) else 0.0
        self.previous.fill_(cost)
        self.started.fill_(True)
        lam = max(0.0, self.kp * e + self.ki * float(self.integral) + self.kd * rise)
        self.value.fill_(lam)
        return lam


@dataclasses.dataclass(kw_only=True)
class PPO_LAG_CFG(PPO_CFG):
    """PPO settings plus the constraint's."""

    cost_limit: float = 5.0  # discounted cost units (see the module docstring)
    pid_gains: tuple[float, float, float] = (0.05, 0.0005, 0.1)  # Kp, Ki, Kd (reference)
    cost_learning_rate: float = 1e-4  # V_c's Adam learning rate


class PPOLagrangian(PPO):
    """skrl PPO with a cost value network (``models["cost_value"]``) and a PID lambda."""

    def __init__(self, *, models, cfg: PPO_LAG_CFG, **kwargs) -> None:
        super().__init__(models=models, cfg=cfg, **kwargs)
        self.cost_value = models["cost_value"]
        self.cost_optimizer = self.cost_value.attach(self, self.cfg.cost_learning_rate)
        self.lagrangian = PIDLagrangian(*self.cfg.pid_gains).to(self.device)
        self.checkpoint_modules["lagrangian"] = self.lagrangian
        self._current_cost_values = None

    def init(self, *, trainer_cfg=None) -> None:
        super().init(trainer_cfg=trainer_cfg)
        for name in ("costs", "cost_values", "cost_returns", "cost_advantages"):
            self.memory.create_tensor(name=name, size=1, dtype=torch.float32)

    def act(self, observations, states, *, timestep: int, timesteps: int):
        actions, outputs = super().act(observations, states, timestep=timestep, timesteps=timesteps)
        if self.training:
            inputs = {"observations": self._observation_preprocessor(observations)}
            self._current_cost_values, _ = self.cost_value.act(inputs, role="cost_value")
        return actions, outputs

    def record_transition(self, *, infos, truncated, next_observations, **kwargs) -> None:
        if self.training:
            if "cost" not in infos:
                raise KeyError("ppo-lag needs info['cost'] from the env (the surgery task has it)")
            costs = infos["cost"].to(torch.float32).view(-1, 1)
            if self.cfg.time_limit_bootstrap and truncated.any():
                with torch.no_grad():
                    inputs = {"observations": self._observation_preprocessor(next_observations)}
                    next_cv, _ = self.cost_value.act(inputs, role="cost_value")
                costs = costs + self.cfg.discount_factor * next_cv * truncated
            i = self.memory.memory_index  # the row PPO's add_samples fills next
            self.memory.tensors["costs"][i].copy_(costs)
            self.memory.tensors["cost_values"][i].copy_(self._current_cost_values)
        super().record_transition(
            infos=infos, truncated=truncated, next_observations=next_observations, **kwargs
        )

    def update(self, *, timestep: int, timesteps: int) -> None:
        cfg, mem = self.cfg, self.memory
        with torch.no_grad():
            inputs = {
                "observations": self._observation_preprocessor(self._current_next_observations),
                "states": self._state_preprocessor(self._current_next_states),  # None: unused
            }
            self.value.enable_training_mode(False)
            last_values, _ = self.value.act(inputs, role="value")
            self.value.enable_training_mode(True)
            last_values = self._value_preprocessor(last_values, inverse=True)
            last_cost_values, _ = self.cost_value.act(inputs, role="cost_value")
        gae = dict(
            terminated=mem.get_tensor_by_name("terminated"),
            truncated=mem.get_tensor_by_name("truncated"),
            discount_factor=cfg.discount_factor,
            lambda_coefficient=cfg.gae_lambda,
            time_limit_bootstrap=cfg.time_limit_bootstrap,
        )
        values = mem.get_tensor_by_name("values")
        returns, advantages = compute_gae(
            rewards=mem.get_tensor_by_name("rewards"),
            values=values,
            last_values=last_values,
            **gae,
        )
        cost_returns, cost_advantages = compute_gae(
            rewards=mem.get_tensor_by_name("costs"),
            values=mem.get_tensor_by_name("cost_values"),
            last_values=last_cost_values,
            **gae,
        )
        mem.set_tensor_by_name("values", self._value_preprocessor(values, train=True))
        mem.set_tensor_by_name("returns", self._value_preprocessor(returns, train=True))
        mem.set_tensor_by_name("advantages", advantages)
        mem.set_tensor_by_name("cost_returns", cost_returns)
        mem.set_tensor_by_name("cost_advantages", cost_advantages)
        j_c = float(cost_returns.mean())
        lam = self.lagrangian.update(j_c, cfg.cost_limit)

        names = [
            "observations",
            "actions",
            "log_prob",
            "values",
            "returns",
            "advantages",
            "cost_returns",
            "cost_advantages",
        ]
        privileged = self.state_space is not None  # a privileged critic reads the states too
        if privileged:
            names.append("states")
        sums = {"policy": 0.0, "value": 0.0, "cost_value": 0.0}
        n_batches = 0
        for epoch in range(cfg.learning_epochs):
            kls = []
            for obs, act, old_logp, old_v, ret, adv, c_ret, c_adv, *states in mem.sample(
                names=names, batch_size=len(mem), mini_batches=cfg.mini_batches
            ):
                inputs = {"observations": self._observation_preprocessor(obs, train=not epoch)}
                if privileged:
                    inputs["states"] = self._state_preprocessor(states[0], train=not epoch)
                _, out = self.policy.act({**inputs, "taken_actions": act}, role="policy")
                log_ratio = out["log_prob"] - old_logp
                with torch.no_grad():
                    kls.append(((torch.exp(log_ratio) - 1) - log_ratio).mean())
                ratio = torch.exp(log_ratio)
                clipped = torch.clip(ratio, 1.0 - cfg.ratio_clip, 1.0 + cfg.ratio_clip)
                reward_loss = -torch.min(adv * ratio, adv * clipped).mean()
                cost_loss = (ratio * c_adv).mean()
                policy_loss = (reward_loss + lam * cost_loss) / (1.0 + lam)
                v, _ = self.value.act(inputs, role="value")
                if cfg.value_clip > 0:
                    v = old_v + torch.clip(v - old_v, -cfg.value_clip, cfg.value_clip)
                value_loss = cfg.value_loss_scale * F.mse_loss(ret, v)
                cv, _ = self.cost_value.act(inputs, role="cost_value")
                cost_value_loss = F.mse_loss(c_ret, cv)

                self.optimizer.zero_grad()
                self.cost_optimizer.zero_grad()
                (policy_loss + value_loss + cost_value_loss).backward()
                if cfg.grad_norm_clip > 0:
                    params = self.policy.parameters()
                    if self.value is not self.policy:
                        params = itertools.chain(params, self.value.parameters())
                    nn.utils.clip_grad_norm_(params, cfg.grad_norm_clip)
                    nn.utils.clip_grad_norm_(self.cost_value.parameters(), cfg.grad_norm_clip)
                self.optimizer.step()
                self.cost_optimizer.step()
                sums["policy"] += policy_loss.item()
                sums["value"] += value_loss.item()
                sums["cost_value"] += cost_value_loss.item()
                n_batches += 1
            if self.scheduler:
                if isinstance(self.scheduler, KLAdaptiveLR):
                    self.scheduler.step(torch.stack(kls).mean().item())
                else:
                    self.scheduler.step()

        n = max(n_batches, 1)
        self.track_data("Loss / Policy loss", sums["policy"] / n)
        self.track_data("Loss / Value loss", sums["value"] / n)
        self.track_data("Loss / Cost value loss", sums["cost_value"] / n)
        self.track_data("Lagrangian / lambda", lam)
        self.track_data("Lagrangian / cost return (mean)", j_c)
        self.track_data(
            "Policy / Standard deviation", self.policy.distribution().stddev.mean().item()
        )
        if self.scheduler:
            self.track_data("Learning / Learning rate", self.scheduler.get_last_lr()[0])
