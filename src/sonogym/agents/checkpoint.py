"""Load a trained policy from a run directory written by ``sonogym.agents.train``."""

from __future__ import annotations

import json
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch

from sonogym.agents.adapter import ObsLayout
from sonogym.agents.networks import SharedActorCritic, make_models


def load_policy(
    run: str | Path, checkpoint: str | Path | None = None, device: str = "cpu"
) -> tuple[SharedActorCritic, dict]:
    """(policy-and-value module in eval mode, the run's resolved config) from ``run``.

    ``checkpoint``: a path, or None for the newest ``checkpoints/agent_<t>.pt``. The module
    takes the adapter's flat observations (``config["obs_layout"]``); its deterministic action
    is ``module.act({"observations": x}, role="policy")[1]["mean_actions"]``.
    """
    from sonogym.agents.train import latest_checkpoint

    run = Path(run)
    cfg_path = run / "config.json"
    if not cfg_path.exists():
        raise FileNotFoundError(f"{cfg_path} not found: is {run} a `sonogym train` run directory?")
    cfg = json.loads(cfg_path.read_text())
    if checkpoint is None:
        found = latest_checkpoint(run)
        if found is None:
            raise FileNotFoundError(f"no checkpoints/agent_<t>.pt in {run}")
        checkpoint = found[0]
    layout = ObsLayout(
        tuple(cfg["obs_layout"]["keys"]),
        tuple(tuple(s) for s in cfg["obs_layout"]["shapes"]),
    )
    low = np.asarray(cfg["action_space"]["low"], np.float32)
    high = np.asarray(cfg["action_space"]["high"], np.float32)
    box = gym.spaces.Box(low, high, dtype=np.float32)
    model = make_models(cfg["task"], layout, box, device, run_net(cfg))["policy"]
    state = torch.load(checkpoint, map_location=device, weights_only=False)
    model.load_state_dict(state["policy"])
    model.eval()
    return model, cfg


def load_cost_critic(run: str | Path, checkpoint: str | Path | None = None, device: str = "cpu"):
    """(cost critic in eval mode, filter threshold) of a ``ppo-sf`` run."""
    from sonogym.agents.safety_filter import CostCritic
    from sonogym.agents.train import latest_checkpoint

    policy, cfg = load_policy(run, checkpoint, device)
    if cfg["algo"] != "ppo-sf":
        raise ValueError(f"{run} is a {cfg['algo']} run; only ppo-sf runs have a cost critic")
    if checkpoint is None:
        checkpoint = latest_checkpoint(run)[0]
    critic = CostCritic(
        cfg["task"], policy.encoder.layout, policy.action_space, device, run_net(cfg)
    )
    state = torch.load(checkpoint, map_location=device, weights_only=False)
    critic.load_state_dict(state["cost_critic"])
    critic.eval()
    return critic, float(cfg["task_config"]["cost_threshold"])


def run_net(cfg: dict) -> str:
    """The conv trunk size a run was trained with (runs before the option existed: "paper")."""
    return cfg["task_config"].get("net", "paper")
