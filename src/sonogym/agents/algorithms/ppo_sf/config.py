"""PPO + safety filter's settings (``ppo-sf``): a task's PPO table plus the cost critic's and
the test-time filter's (reference values; see ``sonogym.agents.algorithms.ppo_sf.agent``)."""

from __future__ import annotations

from dataclasses import dataclass

from sonogym.agents.algorithms.ppo.config import PPOParams

#: How the filter replaces an action whose Q_c exceeds the threshold: "zero" (the paper and
#: reference: no motion) or "search" (ours: the nearest candidate action the critic predicts
#: safe; see ``agent.filter_actions``).
FILTER_MODES = ("zero", "search")


def check_filter_mode(mode: str) -> None:
    """Raise ValueError naming the known modes unless ``mode`` is one of ``FILTER_MODES``."""
    if mode not in FILTER_MODES:
        raise ValueError(f"unknown safety filter mode {mode!r}; choose from {list(FILTER_MODES)}")


@dataclass(frozen=True)
class PPOSafetyFilterParams(PPOParams):
    """PPO's settings plus the cost critic's and the safety filter's; ``from_ppo(table)``
    puts them on a task's PPO table."""

    cost_learning_rate: float = 1e-4  # Adam lr of the cost critic, per optimiser step (reference)
    cost_threshold: float = 0.5  # filter where Q_c(o, a) > this (reference; cost c in [0, 1])
    filter_mode: str = "search"  # at test time: "search" (ours) or "zero" (the paper's)

    def __post_init__(self) -> None:
        super().__post_init__()
        check_filter_mode(self.filter_mode)


def filter_settings(cfg: dict) -> tuple[float, str]:
    """(threshold, mode) of a run's safety filter, from its config.json (``run_config``'s
    layout; runs written before the mode existed get today's default)."""
    params = cfg["algo_params"]
    mode = params.get("filter_mode", PPOSafetyFilterParams.filter_mode)
    return float(params["cost_threshold"]), mode


def resolve_filter(cfg: dict, given: dict) -> dict:
    """The filter a run is evaluated with: its mode and threshold, ``given``'s on top. Raises
    ValueError for an unknown setting or mode, or a threshold outside [0, 1] (Q_c estimates a
    cost in {0, 1})."""
    unknown = sorted(set(given) - {"mode", "threshold"})
    if unknown:
        raise ValueError(f"unknown safety filter settings {unknown}; use mode and threshold")
    threshold, mode = filter_settings(cfg)
    out = {"mode": given.get("mode", mode), "threshold": float(given.get("threshold", threshold))}
    check_filter_mode(out["mode"])
    if not 0.0 <= out["threshold"] <= 1.0:
        raise ValueError(
            f"safety filter threshold must be in [0, 1] (a cost), got {out['threshold']}"
        )
    return out
