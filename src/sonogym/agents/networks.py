"""Per-task shared-trunk actor-critic networks (skrl models), as the paper and reference use.

One module holds one encoder ("trunk") with two heads: a Gaussian policy head (mean, plus a
state-independent log-std parameter initialised at the task's ``init_log_std`` (task
registry), clipped to [-20, 2] by skrl and, where the task anneals exploration, to a ceiling the
trainer lowers step by step (``log_std_ceiling``); actions are not clipped, the env clips them)
and a scalar value head. skrl calls the same object as ``models["policy"]`` and ``models["value"]``
(reference: ``separate: False``).

Inputs are the adapter's flat observations; ``ObsLayout`` un-flattens them. Architectures
(the authors' reference code's; ReLU convs without padding, ELU MLPs):

* navigation: image (1, H, W) -> conv 32 k8 s2, 64 k4 s2, 64 k4 s2, 64 k3 s1 -> flatten ->
  [512, 256, 128]. With the adapter's ``obs_downsample`` F the image is (1, H/F, W/F) and the
  flatten size follows (F <= 2 for the 200 x 150 image; larger F leave no room for 4 convs).
* reconstruction: ``reconstruction`` (40, 40, 40) as 40 channels of 40 x 40 images -> conv
  32 k8 s2, 64 k4 s2, 64 k3 s1 -> 64*5*5; ``path_length`` -> [128, 128, 64]; concat ->
  [512, 256, 128]. 2-D convolutions over 40 channels (the reference's choice) rather than 3-D:
  a 3-D k8 conv over 40^3 costs ~40x the multiply-adds of the 2-D one for the same receptive
  field in the scan plane, and the volume's axes are probe-aligned (depth = channels), so
  the 2-D trunk already sees every voxel.
* surgery: ``image`` (5, 50, 37) -> conv 32 k8 s2, 64 k4 s2, 64 k3 s1 -> 64*8*4; ``pose``
  split into position (3) -> [128, 128, 64] and quaternion (4) -> [128, 128, 64]; concat ->
  [512, 256, 128].

Vector-only observations (``obs_mode="state"``) get one [128, 128, 64] MLP per entry.

``net="small"`` keeps each task's layer count and MLPs but uses narrower, smaller-kernel convs
(16 k5 s2, 32 k3 s2, [32 k3 s2,] 32 k3 s1), for CPU training on downsampled images: on the
navigation image at ``obs_downsample=4`` (50 x 37) it costs ~0.8 M multiply-adds per sample
against ~22 M for the paper's trunk at ``obs_downsample=2``, and it fits inputs the paper's
k8 kernels do not.

``net="lean"`` has the small convs, a [256, 128, 64] trunk and ReLU in every MLP: about half
the PPO update's multiply-adds of ``small`` and a cheaper activation, for surgery state runs
on one CPU core, where the update is compute-bound (``NET_SIZES``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import torch
from skrl.models.torch import DeterministicMixin, GaussianMixin, Model
from torch import nn

from sonogym.agents.adapter import ObsLayout
from sonogym.agents.task_defaults import training_defaults

VECTOR_MLP = (128, 128, 64)
TRUNK_MLP = (512, 256, 128)
PRIVILEGED_MLP = (128, 128)  # hidden layers of the privileged critic's state branch


@dataclass(frozen=True)
class NetSize:
    """What a network size (``net``) sets: the conv layers (a key of the task's ``trunks``),
    the MLP the encoder's features pass through, and the MLPs' activation."""

    convs: str
    trunk: tuple[int, ...]
    activation: type[nn.Module]


#: ``lean``: the small convs, a trunk half as wide and ReLU instead of ELU. Why: on one CPU
#: core a surgery state run's PPO update is compute-bound (GEMMs 57 %, ELU 20 % of it), so a
#: narrower trunk and a cheaper activation roughly halve it (benchmarks/README.md, "RL
#: training (CPU)").
NET_SIZES: dict[str, NetSize] = {
    "paper": NetSize("paper", TRUNK_MLP, nn.ELU),
    "small": NetSize("small", TRUNK_MLP, nn.ELU),
    "lean": NetSize("small", (256, 128, 64), nn.ReLU),
}


def net_size(net: str) -> NetSize:
    if net not in NET_SIZES:
        raise ValueError(f"unknown net {net!r}; choose from {list(NET_SIZES)}")
    return NET_SIZES[net]


def conv_spec(task: str, net: str = "paper"):
    """The (out_channels, kernel, stride) layers of ``task``'s conv trunk for size ``net``
    (the task's ``TrainingDefaults.trunks``)."""
    trunks = training_defaults(task).trunks
    convs = net_size(net).convs
    if convs not in trunks:
        raise ValueError(f"task {task!r} has no {convs!r} conv trunk; it has {list(trunks)}")
    return trunks[convs]


def mlp(
    in_features: int, sizes: tuple[int, ...], activation: type[nn.Module] = nn.ELU
) -> nn.Sequential:
    layers: list[nn.Module] = []
    for out in sizes:
        layers += [nn.Linear(in_features, out), activation()]
        in_features = out
    return nn.Sequential(*layers)


def init_flat_model(model: Model, layout: ObsLayout, action_space: gym.spaces.Box, device) -> None:
    """skrl ``Model.__init__`` for a module that takes the adapter's flat observations."""
    obs_space = gym.spaces.Box(-float("inf"), float("inf"), (layout.size,))
    Model.__init__(model, observation_space=obs_space, action_space=action_space, device=device)


class CostModel(DeterministicMixin, Model):
    """A deterministic cost model on its own task encoder (``Encoder``) and the head its
    subclass adds (``add_head``): the safety filter's cost critic, the Lagrangian's cost value.
    ``ROLE`` is its skrl role and its key in an agent's models."""

    ROLE = ""

    def __init__(
        self, task: str, layout: ObsLayout, action_space: gym.spaces.Box,
        device: str | torch.device | None = None, net: str = "paper",
    ) -> None:  # fmt: skip
        init_flat_model(self, layout, action_space, device)
        DeterministicMixin.__init__(self, clip_actions=False, role=self.ROLE)
        self.encoder = Encoder(task, layout, net)
        self.add_head(int(action_space.shape[0]))
        self.to(self.device)

    def add_head(self, action_dim: int) -> None:
        """Build the layers after the encoder (``encoder.out_features`` inputs)."""
        raise NotImplementedError

    def attach(self, agent: Any, learning_rate: float) -> torch.optim.Adam:
        """Its own Adam optimiser (the policy's does not train it); the model and the
        optimiser are saved in ``agent``'s checkpoints as ``ROLE`` and "cost_optimizer"."""
        optimizer = torch.optim.Adam(self.parameters(), lr=learning_rate)
        agent.checkpoint_modules[self.ROLE] = self
        agent.checkpoint_modules["cost_optimizer"] = optimizer
        return optimizer


def conv_stack(in_shape: tuple[int, int, int], spec) -> tuple[nn.Sequential, int]:
    """ReLU conv stack over (C, H, W) inputs -> (module, flattened output size)."""
    layers: list[nn.Module] = []
    c = in_shape[0]
    for out, k, s in spec:
        layers += [nn.Conv2d(c, out, k, s), nn.ReLU()]
        c = out
    layers.append(nn.Flatten())
    net = nn.Sequential(*layers)
    h, w = in_shape[1:]
    for _, k, s in spec:
        h, w = (h - k) // s + 1, (w - k) // s + 1
        if h < 1 or w < 1:
            raise ValueError(
                f"image of shape {in_shape} is too small for the {len(spec)}-conv trunk "
                f"(kernels {[k for _, k, _ in spec]}); use a smaller obs_downsample"
            )
    return net, c * h * w


class Encoder(nn.Module):
    """Per-entry branches (conv for images, MLP for vectors) concatenated into the trunk MLP
    (``NET_SIZES[net].trunk``)."""

    def __init__(self, task: str, layout: ObsLayout, net: str = "paper") -> None:
        super().__init__()
        convs = conv_spec(task, net)
        size_spec = net_size(net)
        act = size_spec.activation
        self.layout = layout
        self.branches = nn.ModuleDict()
        # vector entries split into parts with one MLP each (surgery: position + quaternion)
        self.splits = {
            k: v for k, v in training_defaults(task).vector_splits.items() if k in layout.keys
        }
        total = 0
        for key, shape in zip(layout.keys, layout.shapes, strict=True):
            if len(shape) == 3:
                net, n = conv_stack(shape, convs)
            elif len(shape) == 1 and key in self.splits:
                parts = self.splits[key]
                if sum(size for _, size in parts) != shape[0]:
                    raise ValueError(f"entry {key!r} of size {shape[0]} cannot split as {parts}")
                net = nn.ModuleDict({name: mlp(k, VECTOR_MLP, act) for name, k in parts})
                n = len(parts) * VECTOR_MLP[-1]
            elif len(shape) == 1:
                net, n = mlp(shape[0], VECTOR_MLP, act), VECTOR_MLP[-1]
            else:
                raise ValueError(f"observation entry {key!r} has unsupported shape {shape}")
            self.branches[_name(key)] = net
            total += n
        self.trunk = mlp(total, size_spec.trunk, act)
        self.out_features = size_spec.trunk[-1]

    def forward(self, flat: torch.Tensor) -> torch.Tensor:
        obs = self.layout.unflatten(flat)
        feats = []
        for key in self.layout.keys:
            net, x = self.branches[_name(key)], obs[key]
            if key in self.splits:  # e.g. surgery pose: position (m) + quaternion
                sizes = [size for _, size in self.splits[key]]
                parts = torch.split(x, sizes, dim=-1)
                feats += [
                    net[name](p) for (name, _), p in zip(self.splits[key], parts, strict=True)
                ]
            else:
                feats.append(net(x))
        return self.trunk(torch.cat(feats, dim=-1))


def _name(key: str) -> str:
    return "obs" if key == "_" else key


class SharedActorCritic(GaussianMixin, DeterministicMixin, Model):
    """Gaussian policy (role "policy") and value (role "value") over one shared ``Encoder``.

    The trunk's features of the last policy call are reused by the value call on the same
    observation tensor (skrl calls policy then value on the same inputs), so a PPO step runs
    the encoder once.

    ``state_size`` > 0 makes the critic privileged (asymmetric actor-critic): the value adds
    ``privileged_value(states)``, an MLP of the task's privileged state (skrl's ``states``,
    e.g. the probe's pose in the goal frame), to the image value head. Why: the reward is a
    difference of distances to the goal, so the return depends mostly on where the goal is,
    which an image shows poorly; a critic that knows it gives the policy gradient advantages
    with less noise. The policy never reads the state. The MLP's output layer starts at
    zero, so a warm start from a run without it begins with that run's values.
    """

    def __init__(
        self,
        task: str,
        layout: ObsLayout,
        action_space: gym.spaces.Box,
        device: str | torch.device | None = None,
        net: str = "paper",
        init_log_std: float = 0.0,
        init_mean_gain: float = 1.0,
        mean_bound_penalty: float = 0.0,
        bounded_mean: bool = False,
        state_size: int = 0,
    ) -> None:
        init_flat_model(self, layout, action_space, device)
        GaussianMixin.__init__(self, clip_actions=False, clip_log_std=True, role="policy")
        DeterministicMixin.__init__(self, clip_actions=False, role="value")
        self.encoder = Encoder(task, layout, net)
        n_act = int(action_space.shape[0])
        self.mean_head = nn.Linear(self.encoder.out_features, n_act)
        with torch.no_grad():  # a small gain: the untrained policy stands nearly still
            self.mean_head.weight.mul_(init_mean_gain)
            self.mean_head.bias.mul_(init_mean_gain)
        self.log_std = nn.Parameter(torch.full((n_act,), float(init_log_std)))
        # not saved: the trainer sets it from the step count (``log_std_ceiling``) each step
        self.register_buffer("log_std_max", torch.tensor(float("inf")), persistent=False)
        self.value_head = nn.Linear(self.encoder.out_features, 1)
        self.privileged_value: nn.Sequential | None = None
        if state_size > 0:
            out = nn.Linear(PRIVILEGED_MLP[-1], 1)
            nn.init.zeros_(out.weight)
            nn.init.zeros_(out.bias)
            self.privileged_value = nn.Sequential(mlp(state_size, PRIVILEGED_MLP), out)
        if mean_bound_penalty < 0:
            raise ValueError(f"mean_bound_penalty must be >= 0, got {mean_bound_penalty}")
        self.mean_bound_penalty = float(mean_bound_penalty)
        f32 = {"dtype": torch.float32}
        self.register_buffer(
            "action_low", torch.as_tensor(action_space.low, **f32), persistent=False
        )
        self.register_buffer(
            "action_high", torch.as_tensor(action_space.high, **f32), persistent=False
        )
        self.bounded_mean = bool(bounded_mean)
        self._cache: tuple[torch.Tensor, bool, torch.Tensor] | None = None
        self.to(self.device)

    def act(self, inputs, *, role: str = ""):
        if role == "policy":
            return GaussianMixin.act(self, inputs, role=role)
        if role == "value":
            return DeterministicMixin.act(self, inputs, role=role)
        raise ValueError(f"role must be 'policy' or 'value', got {role!r}")

    def features(self, obs: torch.Tensor) -> torch.Tensor:
        grad = torch.is_grad_enabled()
        if self._cache is not None and self._cache[0] is obs and self._cache[1] == grad:
            return self._cache[2]
        feats = self.encoder(obs)
        self._cache = (obs, grad, feats)
        return feats

    def compute(self, inputs, role: str = ""):
        obs = inputs["observations"]
        if role == "policy":
            feats = self.features(obs)
            log_std = torch.minimum(self.log_std, self.log_std_max)
            mean = self.mean_head(feats)
            if self.bounded_mean:
                mean = squash_into_box(mean, self.action_low, self.action_high)
            if self.mean_bound_penalty > 0 and mean.requires_grad:
                mean.register_hook(self._bound_gradient(mean.detach()))
            return mean, {"log_std": log_std.expand(obs.shape[0], -1)}
        feats = self.features(obs)
        self._cache = None  # value is the last call on these inputs
        value = self.value_head(feats)
        if self.privileged_value is not None:
            states = inputs.get("states")
            if states is None:
                raise ValueError(
                    "this critic is privileged: pass the env's states with the observations"
                )
            value = value + self.privileged_value(states)
        return value, {}

    def _bound_gradient(self, mean: torch.Tensor):
        """A gradient hook on the policy mean that adds the gradient of
        ``mean_bound_penalty * batch-mean(sum_i excess_i^2)``, excess = how far mean_i lies
        outside the action box, to whatever loss is back-propagated (PPO's, A2C's).

        Why: the env clips actions, so a mean outside the box acts like the box's edge and
        gets no learning signal once sigma is small (samples never fall inside). A collapsed
        surgery state run had its rotation means at 0.1-1.05 rad against a 0.1 rad box in
        60-85 % of steps. Off by default (0): it kept the means in the box but did not stop
        other seeds from collapsing or stalling, and ``bounded_mean`` keeps the means in the
        box by construction. The penalty is 0 inside the box, so it changes nothing for a mean
        that stays there."""
        excess = torch.relu(mean - self.action_high) - torch.relu(self.action_low - mean)
        extra = (2 * self.mean_bound_penalty / mean.shape[0]) * excess
        return lambda grad: grad + extra


def squash_into_box(raw: torch.Tensor, low: torch.Tensor, high: torch.Tensor) -> torch.Tensor:
    """The policy mean ``c + h tanh((raw - c) / h)`` (c the box's centre, h its half-width):
    inside the box always, and equal to ``raw`` to first order near the centre, so a small
    initial mean head starts as it would unsquashed.

    Why: the env clips actions, so a mean outside the box acts like the box's edge, and once
    sigma is small against the box no sample falls inside: that output gets no learning
    signal and drifts. Surgery's rotation box is +-0.1 rad against sigma 0.05 -> 0.005; in
    its state runs without the squash the rotation means lay outside the box in 60-85 % of
    steps (up to 1.05 rad) and the tilt ran away. The sampled actions stay Gaussian around
    this mean (the env still clips them)."""
    centre, half = (high + low) / 2, (high - low) / 2
    return centre + half * torch.tanh((raw - centre) / half)


def log_std_ceiling(
    step: int, init_log_std: float, final_log_std: float, anneal_steps: int
) -> float:
    """The policy's log-sigma ceiling after ``step`` env steps per env: linear in log space
    from ``init_log_std`` at step 0 to ``final_log_std`` at ``anneal_steps``, then constant
    (so sigma falls geometrically, and a resumed run continues where it stopped)."""
    if anneal_steps <= 0 or step >= anneal_steps:
        return float(final_log_std)
    frac = step / anneal_steps
    return float(init_log_std + frac * (final_log_std - init_log_std))


def make_models(
    task: str,
    layout: ObsLayout,
    action_space: gym.spaces.Box,
    device=None,
    net: str = "paper",
    init_log_std: float = 0.0,
    init_mean_gain: float = 1.0,
    mean_bound_penalty: float = 0.0,
    bounded_mean: bool = False,
    state_size: int = 0,
) -> dict[str, Model]:
    """skrl ``models`` dict: the same ``SharedActorCritic`` as "policy" and "value"
    (``state_size`` > 0: with a privileged critic of a state of that size)."""
    model = SharedActorCritic(
        task, layout, action_space, device, net, init_log_std, init_mean_gain,
        mean_bound_penalty, bounded_mean, state_size,
    )  # fmt: skip
    return {"policy": model, "value": model}
