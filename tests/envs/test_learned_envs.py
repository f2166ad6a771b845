"""simulator="learned" in the envs: nets drawn per env at resets as configured, images of the
declared spaces, interchangeable with the model-based simulator behind one interface."""

from dataclasses import replace

import gymnasium as gym
import pytest
import torch

import sonogym  # noqa: F401
from sonogym.envs.navigation import NavigationEnv
from sonogym.ultrasound import UltrasoundSimulator
from sonogym.ultrasound.learned.shipped import shipped_weights
from sonogym.ultrasound.randomization import randomized_from_display

torch.set_num_threads(1)
FAST = dict(patients=(0,), phantom_spacing=0.002, robot=None)


def test_nets_switch_at_resets_as_configured():
    env = NavigationEnv(4, simulator="learned", learned_nets=(0, 1), **FAST)
    seen = set()
    for seed in range(4):
        obs, _ = env.reset(seed=seed)
        idx = env.scene.nets.index
        seen |= set(idx.tolist())
        assert obs.shape == (4, 1, 200, 150)
        assert 0 <= float(obs.min()) and float(obs.max()) <= 1
    assert seen == {0, 1}
    # the observation of an env is its own net's image of its pose
    sim = env.scene.simulator
    s = env.scene.slices()
    for k in (0, 1):
        alone = sim.simulate(replace(s, net_index=torch.full((4,), k)))
        rows = env.scene.nets.index == k
        assert torch.allclose(obs[rows], alone[rows], atol=1e-5)
    # a partial reset redraws only the reset envs' nets
    before = env.scene.nets.index.clone()
    mask = torch.tensor([True, False, False, False])
    for _ in range(6):
        env.reset(options={"reset_mask": mask})
        assert torch.equal(env.scene.nets.index[1:], before[1:])


def test_single_net_set_uses_only_that_net():
    env = NavigationEnv(3, simulator="learned", learned_nets=(4,), **FAST)
    env.reset(seed=0)
    assert env.scene.simulator.num_nets == 1
    assert env.scene.simulator.meta[0]["net"] == 4
    assert env.scene.nets.index.tolist() == [0, 0, 0]


def test_learned_precision_reaches_the_simulator_and_is_checked():
    env = NavigationEnv(2, simulator="learned", learned_nets=(0,), learned_precision="bfloat16",
                        **FAST)  # fmt: skip
    env.reset(seed=0)
    assert env.scene.simulator.precision == "bfloat16"
    with pytest.raises(ValueError, match="learned_precision must be one of"):
        NavigationEnv(1, simulator="learned", learned_precision="half", **FAST)


@pytest.mark.parametrize("task", ["Navigation", "Surgery"])
def test_learned_images_survive_autoreset(task):
    # Regression: images made under torch.inference_mode could not be updated in place when
    # some envs autoreset, so training crashed at the first episode end.
    kw = FAST if task == "Navigation" else dict(patients=(0,), phantom_spacing=0.002)
    env = gym.make_vec(
        f"SonoGym/{task}-v0", num_envs=2, simulator="learned", episode_length=2, **kw
    )
    obs, _ = env.reset(seed=0)
    ended = 0
    for _ in range(3):
        obs, _, _, truncated, info = env.step(torch.zeros(env.action_space.shape))
        ended += int(truncated.sum())
    assert ended == 2  # both envs ended once, at step 2
    image = obs["image"] if isinstance(obs, dict) else obs
    assert 0 <= float(image.min()) and float(image.max()) <= 1
    env.reset(options={"reset_mask": torch.tensor([True, False])})


def test_user_weights_by_path_and_bad_specs():
    env = NavigationEnv(1, simulator="learned", learned_nets=(str(shipped_weights(2)),), **FAST)
    obs, _ = env.reset(seed=0)
    assert env.scene.simulator.meta[0]["net"] == 2 and obs.shape == (1, 1, 200, 150)
    with pytest.raises(ValueError, match="ships nets 0-4"):
        NavigationEnv(1, simulator="learned", learned_nets=(5,), **FAST)
    with pytest.raises(FileNotFoundError, match="not found"):
        NavigationEnv(1, simulator="learned", learned_nets=("/no/such/net.pt",), **FAST)
    with pytest.raises(ValueError, match="learned"):
        NavigationEnv(1, simulator="gan", **FAST)


def test_learned_and_model_based_are_interchangeable():
    envs = {s: NavigationEnv(2, simulator=s, **FAST) for s in ("physical", "learned")}
    out = {}
    for name, env in envs.items():
        assert isinstance(env.scene.simulator, UltrasoundSimulator)
        obs, info = env.reset(seed=3)
        obs2, r, *_, info2 = env.step(torch.ones(2, 3))
        assert env.observation_space.contains(obs.numpy())
        out[name] = (obs, info["state"], info2["state"], r)
    # same shapes and, since the net draw comes last, the same episode
    assert out["physical"][0].shape == out["learned"][0].shape
    for i in (1, 2, 3):
        assert torch.equal(out["physical"][i], out["learned"][i])
    assert not torch.allclose(out["physical"][0], out["learned"][0])


def test_reconstruction_viewing_image_is_learned():
    env = gym.make_vec(
        "SonoGym/Reconstruction-v0", num_envs=2, simulator="learned", learned_nets=(1, 3), **FAST
    )
    env.reset(seed=0)
    assert set(env.scene.nets.index.tolist()) <= {0, 1}
    img = env.scene.observe("us")
    assert img.shape == (2, 1, 200, 150) and 0 <= float(img.min()) <= float(img.max()) <= 1


def test_surgery_volume_slice_by_slice():
    env = gym.make_vec(
        "SonoGym/Surgery-v0", num_envs=1, simulator="learned", learned_nets=(0,),
        patients=(0,), phantom_spacing=0.002,
    )  # fmt: skip
    obs, _ = env.reset(seed=0)
    obs = obs["image"]
    assert obs.shape == (1, 5, 50, 37)
    assert 0 <= float(obs.min()) and float(obs.max()) <= 1
    sc = env.scene
    s = sc.slicer(sc.probe_pos, sc.probe_rot, sc.patient_index)
    # each elevation slice is the 2-D net applied to that slice alone
    for e in (0, 4):
        one = type(s)(s.ct[:, e : e + 1], s.labels[:, e : e + 1], s.origin[:, e : e + 1],
                      s.row_step, s.col_step, s.seed, s.patient_index, s.probe,
                      torch.zeros(1, dtype=torch.long))  # fmt: skip
        assert torch.allclose(sc.simulator.simulate(one), obs[:, e : e + 1], atol=1e-5)


def test_imaging_randomisation_acts_on_each_envs_own_net():
    """Learned images with the episode's imaging settings: each env's net (carried by its
    slices), then the display-image randomisation of that env's settings."""
    env = NavigationEnv(
        6, simulator="learned", learned_nets=(0, 1), imaging_randomization=True, **FAST
    )
    obs, _ = env.reset(seed=3)
    sc = env.scene
    assert set(sc.nets.index.tolist()) == {0, 1}  # both nets in one batch
    s = sc.slicer(sc.probe_pos, sc.probe_rot, sc.patient_index)
    own = torch.empty_like(obs)
    for k in (0, 1):
        rows = sc.nets.index == k
        own[rows] = sc.simulator.simulate(replace(s, net_index=torch.full((6,), k)))[rows]
    expected = randomized_from_display(own, sc.imaging_settings, sc.probe_geometry)
    assert torch.allclose(obs, expected, atol=1e-5)
    assert (obs - own).abs().mean() > 0.01  # the settings change the images
    ids = torch.tensor([4, 1])
    assert torch.allclose(sc.observe("us", ids), obs[ids], atol=1e-5)


def test_learned_precision_auto_is_bfloat16_only_where_the_cpu_has_it(monkeypatch):
    from sonogym.envs.identity import identity
    from sonogym.envs.navigation import NavigationConfig
    from sonogym.ultrasound.learned import inference

    for native, want in ((True, "bfloat16"), (False, "float32")):
        monkeypatch.setattr(inference, "native_bfloat16", lambda native=native: native)
        assert NavigationConfig(simulator="learned").learned_precision == want
        kw = {"simulator": "learned", "learned_nets": (0,)}
        assert identity("navigation", kw)["ultrasound"]["precision"] == want
    # an explicit precision is kept whatever the CPU, and a bad one named
    assert NavigationConfig(learned_precision="float32").learned_precision == "float32"
    with pytest.raises(ValueError, match="precision must be one of"):
        NavigationConfig(learned_precision="half")
