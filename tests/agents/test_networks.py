"""Per-task actor-critic networks: forward shapes and the shared encoder."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch

from sonogym.agents.adapter import ObsLayout
from sonogym.agents.networks import SharedActorCritic, make_models

LAYOUTS = {
    "navigation": (ObsLayout(("_",), ((1, 200, 150),)), 3),
    "reconstruction": (ObsLayout(("path_length", "reconstruction"), ((1,), (40, 40, 40))), 4),
    "surgery": (ObsLayout(("image", "pose"), ((5, 50, 37), (7,))), 6),
}
# conv output sizes the reference lists (the authors' reference code's)
FLAT = {"navigation": 64 * 20 * 14, "reconstruction": 64 * 5 * 5, "surgery": 64 * 8 * 4}


def _box(n):
    return gym.spaces.Box(-2.0, 2.0, (n,), np.float32)


@pytest.mark.parametrize("task", sorted(LAYOUTS))
def test_forward_shapes_and_shared_encoder(task):
    torch.manual_seed(0)
    layout, n_act = LAYOUTS[task]
    models = make_models(task, layout, _box(n_act))
    policy, value = models["policy"], models["value"]
    assert policy is value  # one module, one encoder
    convs = [m for m in policy.modules() if isinstance(m, torch.nn.Conv2d)]
    assert len(convs) == (4 if task == "navigation" else 3)
    first_linear = policy.encoder.trunk[0]
    vec_feats = first_linear.in_features - FLAT[task]
    assert vec_feats == {"navigation": 0, "reconstruction": 64, "surgery": 128}[task]
    obs = torch.rand(5, layout.size)
    actions, out = policy.act({"observations": obs}, role="policy")
    assert actions.shape == (5, n_act)
    assert out["log_prob"].shape == (5, 1) and out["mean_actions"].shape == (5, n_act)
    values, _ = value.act({"observations": obs}, role="value")
    assert values.shape == (5, 1)
    # the value loss alone trains the shared conv encoder; the policy loss reaches it too
    policy.zero_grad()
    values.sum().backward()
    assert convs[0].weight.grad is not None and convs[0].weight.grad.abs().sum() > 0
    assert policy.mean_head.weight.grad is None
    policy.zero_grad()
    _, out = policy.act({"observations": obs}, role="policy")
    out["mean_actions"].sum().backward()
    assert convs[0].weight.grad.abs().sum() > 0


def test_value_reuses_policy_features_only_for_same_tensor():
    layout, n_act = LAYOUTS["surgery"]
    net = SharedActorCritic("surgery", layout, _box(n_act))
    calls = []
    net.encoder.register_forward_hook(lambda *a: calls.append(1))
    obs = torch.rand(3, layout.size)
    net.act({"observations": obs}, role="policy")
    v1, _ = net.act({"observations": obs}, role="value")
    assert len(calls) == 1
    v2, _ = net.act({"observations": obs.clone()}, role="value")
    assert len(calls) == 2 and torch.allclose(v1, v2)


def test_errors():
    layout, _ = LAYOUTS["navigation"]
    small = ObsLayout(("_",), ((1, 50, 37),))
    with pytest.raises(ValueError, match="obs_downsample"):
        make_models("navigation", small, _box(3))
    # the small trunk fits the 50 x 37 image (obs_downsample 4) with the same 4 convs
    model = make_models("navigation", small, _box(3), net="small")["policy"]
    convs = [m for m in model.encoder.modules() if isinstance(m, torch.nn.Conv2d)]
    assert len(convs) == 4
    assert model.act({"observations": torch.rand(2, small.size)}, role="policy")[0].shape == (2, 3)
    with pytest.raises(ValueError, match="unknown net"):
        make_models("navigation", layout, _box(3), net="huge")
    with pytest.raises(ValueError, match="known tasks"):
        make_models("nope", layout, _box(3))
    with pytest.raises(ValueError, match="role"):
        make_models("navigation", layout, _box(3))["policy"].act(
            {"observations": torch.rand(1, layout.size)}, role="critic"
        )


@pytest.mark.parametrize("task", sorted(LAYOUTS))
def test_lean_net_is_small_convs_a_narrow_trunk_and_relu(task):
    """``lean`` keeps the small convs but halves the trunk and swaps ELU for ReLU; ``paper`` and
    ``small`` keep the paper's [512, 256, 128] ELU trunk (their trained runs load unchanged)."""
    layout, n_act = LAYOUTS[task]
    if task == "navigation":
        layout = ObsLayout(("_",), ((1, 50, 37),))
    nets = {n: make_models(task, layout, _box(n_act), net=n)["policy"] for n in ("small", "lean")}
    small, lean = nets["small"], nets["lean"]
    trunk = [m.out_features for m in lean.encoder.trunk if isinstance(m, torch.nn.Linear)]
    assert trunk == [256, 128, 64] and lean.mean_head.in_features == 64
    assert [m.out_features for m in small.encoder.trunk if isinstance(m, torch.nn.Linear)] == [
        512,
        256,
        128,
    ]
    kinds = {type(m) for m in lean.encoder.modules() if isinstance(m, torch.nn.ReLU | torch.nn.ELU)}
    assert kinds == {torch.nn.ReLU}
    assert torch.nn.ELU in {type(m) for m in small.encoder.modules()}

    def conv_shapes(m):
        return [c.weight.shape for c in m.modules() if isinstance(c, torch.nn.Conv2d)]

    assert conv_shapes(lean) == conv_shapes(small)
    n_params = {n: sum(p.numel() for p in m.parameters()) for n, m in nets.items()}
    assert n_params["lean"] < 0.6 * n_params["small"]
    assert lean.act({"observations": torch.rand(2, layout.size)}, role="policy")[0].shape == (
        2,
        n_act,
    )


def test_privileged_critic_adds_a_state_value_the_policy_never_reads():
    """With ``state_size`` the value is the image value plus an MLP of the privileged state,
    whose output layer starts at zero; the policy's action ignores the state."""
    layout, n_act = LAYOUTS["surgery"]
    torch.manual_seed(0)
    plain = SharedActorCritic("surgery", layout, _box(n_act))
    torch.manual_seed(0)
    priv = SharedActorCritic("surgery", layout, _box(n_act), state_size=6)
    shared = {k: v for k, v in priv.state_dict().items() if not k.startswith("privileged_value.")}
    assert shared.keys() == plain.state_dict().keys()
    plain.load_state_dict(shared)
    obs, states = torch.rand(4, layout.size), torch.rand(4, 6)
    v_plain, _ = plain.act({"observations": obs}, role="value")
    v_priv, _ = priv.act({"observations": obs, "states": states}, role="value")
    assert torch.equal(v_plain, v_priv)  # the state branch starts at zero output
    with torch.no_grad():
        priv.privileged_value[-1].bias.fill_(0.5)
        priv.privileged_value[-1].weight.normal_()
    v1, _ = priv.act({"observations": obs, "states": states}, role="value")
    v2, _ = priv.act({"observations": obs, "states": states.flip(0)}, role="value")
    assert not torch.allclose(v1, v_plain) and not torch.allclose(v1, v2)
    img = priv.value_head(priv.encoder(obs))
    assert torch.allclose(v1 - img, priv.privileged_value(states))
    a1 = priv.act({"observations": obs, "states": states}, role="policy")[1]["mean_actions"]
    a2 = priv.act({"observations": obs, "states": states.flip(0)}, role="policy")[1]
    assert torch.equal(a1, a2["mean_actions"])
    with pytest.raises(ValueError, match="privileged"):
        priv.act({"observations": obs}, role="value")
