"""Checkpoints of a run directory written by ``sonogym.agents.train``: find them (``RL_RUN``,
the RL kind of ``sonogym.runs.RunFolder``), load the trained networks, and act with them in an
env as a ``Policy`` (``rl_policy``; how a run acts is its algorithm's ``Acting``)."""

from __future__ import annotations

import math
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch

from sonogym.agents.adapter import ObsLayout, SkrlEnvAdapter
from sonogym.agents.networks import SharedActorCritic, log_std_ceiling, make_models, net_size
from sonogym.envs.policy import StatelessPolicy
from sonogym.runs import (
    CheckpointError,
    RunFolder,
    RunKind,
    atomic_write_bytes,
    lists_to_tuples,
    load_weights,
)

#: The modules every algorithm's acting reads (an algorithm's ``Acting.modules`` adds its own).
ACTING_MODULES = ("policy", "obs_standardizer")


def acting_modules(algo: str) -> tuple[str, ...]:
    """The checkpoint entries a run of ``algo`` acts with: what a shipped policy keeps (no
    optimiser, no value)."""
    from sonogym.agents.algorithms import get_algorithm

    return ACTING_MODULES + get_algorithm(algo).acting.modules


def read_checkpoint(path: str | Path, device: str | torch.device = "cpu") -> dict:
    """An agent checkpoint (skrl's ``{module name: state}`` dict), read without unpickling
    code (``weights_only=True``): tensors, numbers, strings and containers only. A
    ``.safetensors`` file (``export_acting_weights``) holds the acting modules' tensors."""
    path = Path(path)
    if path.suffix == ".safetensors":
        state = _read_safetensors(path, device)
    else:
        state = load_weights(path, device, "agent checkpoint")
    if not isinstance(state, dict) or "policy" not in state:
        raise CheckpointError(f"{path} is not an agent checkpoint (no 'policy' entry)")
    return state


def _read_safetensors(path: Path, device) -> dict:
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    if not path.is_file():
        raise FileNotFoundError(f"agent weights {path} not found")
    try:
        flat = load_file(str(path), device=str(device))
    except (SafetensorError, OSError, ValueError) as e:
        raise CheckpointError(f"{path} is not a readable safetensors file ({e})") from None
    state: dict[str, dict[str, torch.Tensor]] = {}
    for key, value in flat.items():
        module, sep, name = key.partition("/")
        if not sep:
            raise CheckpointError(f"{path}: tensor {key!r} names no module (module/parameter)")
        state.setdefault(module, {})[name] = value
    return state


def export_acting_weights(
    checkpoint: str | Path, dest: str | Path, modules: tuple[str, ...] = ACTING_MODULES
) -> Path:
    """The acting ``modules`` (``acting_modules(algo)``) of ``checkpoint`` as one safetensors
    file at ``dest`` (tensors ``<module>/<parameter>``; nothing to unpickle), written
    atomically."""
    from safetensors.torch import save

    state = read_checkpoint(checkpoint)
    flat = {
        f"{m}/{k}": v.detach().cpu().contiguous()
        for m in modules
        if m in state
        for k, v in state[m].items()
        if isinstance(v, torch.Tensor)
    }
    return atomic_write_bytes(dest, save(flat))


def load_policy(
    run: str | Path, checkpoint: str | Path | None = None, device: str = "cpu"
) -> tuple[SharedActorCritic, dict]:
    """(policy-and-value module in eval mode, the run's resolved config) from ``run``.

    ``checkpoint``: a path, or None for the newest readable ``checkpoints/agent_<t>.pt`` (an
    unreadable newer one is skipped with a warning naming it). The module
    takes the adapter's flat observations (``config["obs_layout"]``); its deterministic action
    is ``module.act({"observations": x}, role="policy")[1]["mean_actions"]``.
    """
    run = Path(run)
    cfg = run_config(run)
    check_obs_version(cfg, run / "config.json")  # reading its logs (report) needs no check
    if checkpoint is None:
        checkpoint = newest_checkpoint(run)
    layout = ObsLayout(
        tuple(cfg["obs_layout"]["keys"]),
        tuple(tuple(s) for s in cfg["obs_layout"]["shapes"]),
    )
    low = np.asarray(cfg["action_space"]["low"], np.float32)
    high = np.asarray(cfg["action_space"]["high"], np.float32)
    box = gym.spaces.Box(low, high, dtype=np.float32)
    learning = cfg["task_config"]["learning"]
    bounded = bool(learning.get("bounded_mean", False))  # runs before it: False
    state_size = int(cfg.get("privileged_state_size", 0))  # the critic's; acting ignores it
    model = make_models(
        cfg["task"], layout, box, device, run_net(cfg), bounded_mean=bounded, state_size=state_size
    )["policy"]
    load_module(model, checkpoint, "policy", device)
    set_log_std_ceiling(model, learning, RL_RUN.step_of(checkpoint))
    model.eval()
    return model, cfg


def newest_checkpoint(run: str | Path) -> Path:
    """The run's newest readable ``checkpoints/agent_<t>.pt``."""
    return RunFolder(Path(run), RL_RUN).require_checkpoint().path


def load_module(module: torch.nn.Module, checkpoint: str | Path, key: str, device) -> None:
    """Load entry ``key`` of an agent checkpoint into ``module``; a checkpoint without it, or
    whose tensors do not fit the module the run's config.json describes (a config.json edited,
    or copied from another run), raises ``CheckpointError`` naming both."""
    state = read_checkpoint(checkpoint, device)
    if key not in state:
        raise CheckpointError(
            f"{checkpoint} holds no {key!r} (it holds {sorted(state)}), which the run's "
            "config.json asks for: config.json was edited or is another run's; restore it"
        )
    try:
        module.load_state_dict(state[key])
    except RuntimeError as e:
        detail = " ".join(str(e).split())[:300]
        raise CheckpointError(
            f"{checkpoint}: its {key!r} does not fit the network the run's config.json "
            f"describes ({detail}); config.json was edited or is another run's; restore it"
        ) from None


def set_log_std_ceiling(model: SharedActorCritic, learning: dict, step: int | None) -> None:
    """Cap ``model``'s log sigma where the run anneals exploration (``final_log_std`` of its
    ``task_config.learning``), at its value after ``step`` env steps per env (None: the end of
    the schedule)."""
    final = learning.get("final_log_std")
    if final is None:
        return
    anneal = int(learning.get("anneal_steps", 0))
    ceiling = log_std_ceiling(anneal if step is None else step, learning["init_log_std"],
                              final, anneal)  # fmt: skip
    model.log_std_max.fill_(ceiling)


#: Keys every run's ``config.json`` has (what evaluation reads).
RUN_CONFIG_KEYS = ("task", "algo", "seed", "obs_layout", "action_space", "task_config")


def run_config(run: str | Path) -> dict:
    """A run's ``config.json``, with a clear error if it is missing, malformed, incomplete or
    hand-edited into something no run has (``check_run_config``)."""
    from sonogym.agents.configs import upgrade_config
    from sonogym.envs.registry import check_task_name
    from sonogym.runs import read_json

    path = Path(run) / "config.json"
    cfg = read_json(path, "`sonogym train` run folder", RUN_CONFIG_KEYS)
    check_task_name(cfg["task"], path)  # it names files (eval, plots)
    try:
        cfg = upgrade_config(cfg)  # today's layout, whenever the run was written
        check_run_config(cfg)
    except ValueError as e:
        raise ValueError(
            f"{path}: {e}; restore the config.json the run wrote, or retrain the run"
        ) from None
    return cfg


def check_run_config(cfg: dict) -> None:
    """Refuse, naming the key, what evaluation would otherwise trip over late: an unknown task
    or an algorithm the task has no run of, values of the wrong type, an observation layout or
    action box that is not a list of the right sizes, and env options the task's env refuses."""
    from sonogym.agents.algorithms import check_algo
    from sonogym.envs.registry import env_config, get_task

    def expect(ok: bool, what: str) -> None:
        if not ok:
            raise ValueError(what)

    for key in ("task", "algo"):
        expect(isinstance(cfg[key], str), f"{key} must be a name, got {cfg[key]!r}")
    check_algo(cfg["task"], cfg["algo"])
    spec = get_task(cfg["task"])
    expect(_is_int(cfg["seed"]), f"seed must be an integer, got {cfg['seed']!r}")
    params = cfg.get("algo_params")
    expect(isinstance(params, dict), f"algo_params must be an object, got {params!r}")
    tc = cfg["task_config"]
    expect(isinstance(tc, dict), f"task_config must be an object, got {tc!r}")
    learning = tc.get("learning")
    expect(isinstance(learning, dict), f"task_config.learning must be an object, got {learning!r}")
    missing = [k for k in ("env_kwargs", "obs_downsample") if k not in tc]
    missing += ["learning.obs_scales"] if "obs_scales" not in learning else []
    expect(not missing, f"task_config lacks {missing}")
    expect(isinstance(tc["env_kwargs"], dict), "task_config.env_kwargs must be an object")
    env_cfg = env_config(cfg["task"], lists_to_tuples(tc["env_kwargs"]))
    expect(
        _is_int(tc["obs_downsample"]) and tc["obs_downsample"] >= 1,
        f"task_config.obs_downsample must be an integer >= 1, got {tc['obs_downsample']!r}",
    )
    scales = learning["obs_scales"]
    expect(
        isinstance(scales, dict) and all(_is_number(v) for v in scales.values()),
        f"task_config.learning.obs_scales must map entries to finite numbers, got {scales!r}",
    )
    net_size(run_net(cfg))
    layout = cfg["obs_layout"]
    keys, shapes = (
        (layout.get("keys"), layout.get("shapes")) if isinstance(layout, dict) else (0, 0)
    )
    expect(
        isinstance(keys, list)
        and isinstance(shapes, list)
        and len(keys) == len(shapes) > 0
        and all(isinstance(k, str) for k in keys)
        and all(isinstance(sh, list) and all(_is_int(n) and n >= 1 for n in sh) for sh in shapes),
        "obs_layout must hold 'keys' (names) and 'shapes' (lists of sizes >= 1), one per key",
    )
    # a force action (``force_action``) adds one component to the task's
    box = cfg["action_space"]
    dim = len(spec.action_names) + int(bool(getattr(env_cfg, "force_action", False)))
    for side in ("low", "high"):
        v = box.get(side) if isinstance(box, dict) else None
        expect(
            isinstance(v, list) and len(v) == dim and all(_is_number(x) for x in v),
            f"action_space.{side} must list {dim} finite numbers ({cfg['task']} actions), "
            f"got {v!r}",
        )


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_number(v) -> bool:
    return _is_int(v) or (isinstance(v, float) and math.isfinite(v))


def check_obs_version(cfg: dict, where: str | Path) -> None:
    """Refuse a run whose policy read an observation that has since changed meaning
    (``TaskSpec.obs_versions``; runs from before versions were recorded read version 1)."""
    from sonogym.envs.registry import get_task

    mode = cfg["task_config"].get("env_kwargs", {}).get("obs_mode")
    trained, now = int(cfg.get("obs_version", 1)), get_task(cfg["task"]).obs_version(mode)
    if trained != now:
        raise ValueError(
            f"{where}: the policy was trained on version {trained} of the {cfg['task']} "
            f"observation {mode or '(default)'!r}; this sonogym emits version {now} (see the "
            "task's docstring). Retrain the run, or evaluate it with the sonogym it was "
            f"trained with ({cfg.get('versions', {}).get('sonogym', 'unknown')})"
        )


def run_net(cfg: dict) -> str:
    """The conv trunk size a run was trained with (runs before the option existed: "paper")."""
    return cfg["task_config"].get("net", "paper")


class RLPolicy(StatelessPolicy):
    """A trained run acting deterministically (the Gaussian's mean action) on an env's
    observations, flattened as in training."""

    def __init__(self, model, adapter: SkrlEnvAdapter):
        self.model = model
        self.adapter = adapter

    def act(self, obs, info) -> torch.Tensor:
        x = self.adapter.flatten(obs)
        return self.model.act({"observations": x}, role="policy")[1]["mean_actions"]


def rl_policy(
    run: str | Path, env, checkpoint: str | Path | None = None, device: str = "cpu",
    controller: str = "policy", settings: dict | None = None,
):  # fmt: skip
    """The run's policy acting in ``env`` (an env of the run's task), as its algorithm acts
    (``Acting.policy``: a ``ppo-sf`` run through its safety filter): evaluation controller
    ``controller`` ("policy" or one the algorithm adds), with the algorithm's test-time
    ``settings`` (None: the run's own)."""
    from sonogym.agents.algorithms import ActingSetup, get_algorithm

    model, cfg = load_policy(run, checkpoint, device)
    tc = cfg["task_config"]
    adapter = SkrlEnvAdapter(
        env, tc["obs_downsample"], tc["learning"]["obs_scales"],
        standardize_vectors=tc["learning"].get("standardize_vectors", False),
    )  # fmt: skip
    checkpoint = Path(checkpoint) if checkpoint is not None else newest_checkpoint(run)
    if adapter.standardizer is not None:
        load_module(adapter.standardizer, checkpoint, "obs_standardizer", device)
    policy, acting = RLPolicy(model, adapter), get_algorithm(cfg["algo"]).acting
    if acting.policy is None:
        return policy
    if settings is None:
        settings = acting.settings.resolve(cfg, {}) if acting.settings is not None else {}
    setup = ActingSetup(policy, Path(run), cfg, checkpoint, device, controller, settings)
    return acting.policy(setup)


#: How ``sonogym.runs.RunFolder`` reads an RL run: checkpoints ``agent_<t>.pt`` (t: env steps
#: per env), config.json without a "kind".
RL_RUN = RunKind(
    name="rl",
    command="sonogym train",
    marker=None,
    checkpoint_name=r"agent_(\d+)\.pt",
    checkpoint_hint="agent_<t>.pt",
    read_checkpoint=read_checkpoint,
    read_config=run_config,
    env_kwargs_key=("task_config", "env_kwargs"),
)
