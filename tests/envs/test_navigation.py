import math
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env

import sonogym  # noqa: F401
from sonogym.envs.navigation import (
    NavigationEnv,
    navigation_expert,
    navigation_reward,
    probe_tilt,
)

FAST = dict(patients=(0,), phantom_spacing=0.002)


def _env(n, **kw):
    return gym.make_vec("SonoGym/Navigation-v0", num_envs=n, **{**FAST, **kw})


def test_make_vec_gives_the_native_batched_env():
    env = _env(3, obs_mode="state", robot=None)
    assert isinstance(env, NavigationEnv)
    assert env.num_envs == 3
    assert env.metadata["autoreset_mode"] == gym.vector.AutoresetMode.SAME_STEP


def test_single_env_passes_gymnasium_checker():
    env = gym.make("SonoGym/Navigation-v0", **FAST)
    check_env(env.unwrapped, skip_render_check=True)


def test_observation_matches_its_declared_space():
    env = _env(2)
    obs, info = env.reset(seed=0)
    assert obs.shape == (2, 1, 200, 150) and obs.dtype == torch.float32
    assert env.observation_space.contains(obs.numpy())
    assert 0.0 <= float(obs.min()) and float(obs.max()) <= 1.0
    assert float(obs.std()) > 0.01  # an image, not a constant
    lab_env = _env(2, obs_mode="labels", robot=None)
    lab, _ = lab_env.reset(seed=0)
    assert lab.dtype == torch.uint8 and lab_env.observation_space.contains(lab.numpy())
    assert {118, 119} <= set(torch.unique(lab).tolist())  # the image starts at the skin


def test_reward_is_the_papers_formula_on_recorded_transitions():
    env = _env(8, obs_mode="state", robot=None)
    _, info = env.reset(seed=1)
    g = torch.Generator().manual_seed(0)
    for _ in range(20):
        before = info["state"].double().numpy()
        a = (torch.rand(8, 3, generator=g) * 4 - 2).numpy()
        _, r, _, _, info = env.step(a)
        after = info["state"].double().numpy()
        want = 0.045 * 1e3 * (
            np.linalg.norm(before[:, :3], axis=1) - np.linalg.norm(after[:, :3], axis=1)
        ) + (np.linalg.norm(before[:, 3:], axis=1) - np.linalg.norm(after[:, 3:], axis=1))
        assert np.allclose(r.numpy(), want, atol=1e-4)


def test_reward_of_a_known_step():
    p0 = torch.tensor([[0.010, 0.0, 0.0]])
    p1 = torch.tensor([[0.007, 0.0, 0.0]])
    q0 = torch.tensor([[0.0, 0.0, 0.5]])
    q1 = torch.tensor([[0.0, 0.0, 0.4]])
    r = navigation_reward(p0, q0, p1, q1, 0.045)
    assert r.item() == pytest.approx(0.045 * 3 + 0.1)


def test_expert_reaches_the_goal_and_random_does_not():
    n = 64
    env = _env(n, obs_mode="state")
    _, info = env.reset(seed=123)
    final = None
    for _ in range(env.episode_length):
        _, _, _, _, info = env.step(navigation_expert(info["state"]))
        final = info.get("final_info", final)
    pos, ang = final["position_error_mm"], final["angle_error_deg"]
    ok = (pos < 2.0) & (ang < 2.0)
    assert ok.all(), (pos.max(), ang.max())
    # a random policy does not
    _, info = env.reset(seed=123)
    g = torch.Generator().manual_seed(1)
    for _ in range(env.episode_length):
        _, _, _, _, info = env.step(torch.rand(n, 3, generator=g) * 4 - 2)
        final = info.get("final_info", final)
    ok = (final["position_error_mm"] < 2.0) & (final["angle_error_deg"] < 2.0)
    assert ok.float().mean() < 0.2


@pytest.mark.parametrize("start_yaw", [(1.5, 1.55), (3.45, 3.5)])
def test_arm_turns_the_probe_the_short_way_from_the_start_yaw_edges(start_yaw):
    # Regression: the integrated yaw command ran > pi ahead of a lagging arm and the IK then
    # turned the probe the wrong way (expert episodes ending 150-170 deg off).
    n = 16
    env = _env(n, obs_mode="state", start_yaw=start_yaw)
    _, info = env.reset(seed=1000)
    final = None
    for _ in range(env.episode_length):
        _, _, _, _, info = env.step(navigation_expert(info["state"]))
        final = info.get("final_info", final)
    assert final["angle_error_deg"].max() < 2.0, final["angle_error_deg"]
    assert final["position_error_mm"].max() < 2.0


def test_same_seed_same_episode_bit_for_bit():
    def run():
        env = _env(3)
        obs, _ = env.reset(seed=7)
        out = [obs]
        g = torch.Generator().manual_seed(3)
        for _ in range(3):
            obs, r, *_ = env.step(torch.rand(3, 3, generator=g) * 4 - 2)
            out += [obs, r]
        return out

    a, b = run(), run()
    assert all(torch.equal(x, y) for x, y in zip(a, b, strict=True))


def test_partial_reset_leaves_other_envs_untouched():
    env = _env(4)
    env.reset(seed=0)
    obs, _, _, _, info = env.step(torch.ones(4, 3))
    mask = torch.tensor([True, False, True, False])
    obs2, info2 = env.reset(options={"reset_mask": mask})
    assert torch.equal(obs2[~mask], obs[~mask])
    assert torch.equal(info2["state"][~mask], info["state"][~mask])
    assert not torch.equal(info2["state"][mask], info["state"][mask])
    assert (env.episode_length_buf[mask] == 0).all() and (env.episode_length_buf[~mask] == 1).all()


def test_autoreset_same_step_returns_final_obs_and_metrics():
    env = _env(2, episode_length=3)
    obs, info = env.reset(seed=0)
    for _ in range(3):
        obs, _, term, trunc, info = env.step(torch.zeros(2, 3))
    assert trunc.all() and not term.any()
    assert info["_final_obs"].all()
    assert info["final_obs"].shape == obs.shape and not torch.equal(info["final_obs"], obs)
    for k in ("position_error_mm", "angle_error_deg", "level_miss", "return"):
        assert info["final_info"][k].shape == (2,)
    assert (env.episode_length_buf == 0).all()


def test_level_miss_counts_episodes_ending_past_20_mm_along_the_spine(monkeypatch):
    from sonogym.envs.navigation import LEVEL_MISS_MM

    env = _env(4, obs_mode="state", robot=None)
    env.reset(seed=0)
    g = env.goal_cmd
    dz = torch.tensor([19.0, 21.0, -25.0, 0.0], dtype=g.dtype) * 1e-3  # along the spine
    dx = torch.tensor([0.0, 0.0, 0.0, 30.0], dtype=g.dtype) * 1e-3  # across it: no level miss
    reached = (g[:, 0] + dx, g[:, 1] + dz, g[:, 2], torch.zeros_like(dz))
    monkeypatch.setattr(env.scene, "measured_command", lambda sl=slice(None): reached)
    assert LEVEL_MISS_MM == 20.0
    assert env.level_miss().tolist() == [0.0, 1.0, 1.0, 0.0]
    m = env._episode_metrics(torch.arange(4))
    assert m["level_miss"].tolist() == [0.0, 1.0, 1.0, 0.0]
    assert torch.allclose(m["position_error_mm"], torch.tensor([19.0, 21.0, 25.0, 30.0]))


def test_bad_actions_and_options_raise():
    env = _env(2, obs_mode="state", robot=None)
    env.reset(seed=0)
    with pytest.raises(ValueError, match="shape"):
        env.step(torch.zeros(3, 3))
    with pytest.raises(ValueError, match="NaN or inf"):
        env.step(torch.tensor([[0.0, math.nan, 0.0], [0.0, 0.0, 0.0]]))
    with pytest.raises(ValueError, match="NaN or inf"):
        env.step(torch.tensor([[0.0, 0.0, math.inf], [0.0, 0.0, 0.0]]))
    with pytest.raises(TypeError, match="valid options"):
        _env(1, obs_mod="us")
    with pytest.raises(ValueError, match="obs_mode"):
        _env(1, obs_mode="rgb")
    with pytest.raises(ValueError, match="simulator"):
        _env(1, simulator="ray-tracer")


def test_envs_spread_over_patients():
    env = _env(4, patients=(0, 1), obs_mode="state", robot=None)
    g = env.goal_cmd
    assert torch.equal(g[0], g[2]) and torch.equal(g[1], g[3])
    assert not torch.equal(g[0], g[1])


def test_action_scaling_and_clipping_in_si_units():
    env = _env(2, obs_mode="state", robot=None)
    env.reset(seed=0)
    before = env.command.clone()
    rot = env.scene.probe_rot.clone()
    env.step(torch.tensor([[1.0, 0.0, 1.0], [5.0, 0.0, -5.0]]))
    d = env.command - before
    step = torch.stack([rot[:, 0, 0], rot[:, 2, 0]], -1)  # x_U in the frontal plane
    assert torch.allclose(d[0, :2], 0.003 * step[0], atol=1e-6)
    assert torch.allclose(d[1, :2], 0.006 * step[1], atol=1e-6)  # clipped to 6 mm
    assert d[0, 2].item() == pytest.approx(0.1) and d[1, 2].item() == pytest.approx(-0.2)


def test_us_heading_observes_the_us_image_and_the_reached_yaw():
    """``us_heading``: the "us" image bit for bit plus (cos, sin) of the reached yaw, which tells
    the goal (yaw pi) from the goal turned 180 deg, where the images look alike."""
    plain, head = _env(4), _env(4, obs_mode="us_heading")
    obs_p, _ = plain.reset(seed=3)
    obs_h, info = head.reset(seed=3)
    assert set(obs_h) == {"image", "heading"}
    assert head.observation_space.contains({k: v.numpy() for k, v in obs_h.items()})
    torch.testing.assert_close(obs_h["image"], obs_p, rtol=0, atol=0)
    yaw = info["measured_command"][:, 2]
    torch.testing.assert_close(obs_h["heading"], torch.stack([yaw.cos(), yaw.sin()], -1))
    act = torch.zeros(4, 3)
    act[:, 2] = 1.0  # turn 0.1 rad
    obs_h, *_, info = head.step(act)
    yaw2 = info["measured_command"][:, 2]
    assert float((yaw2 - yaw).abs().min()) > 0.02  # the arm turned the probe (velocity-limited)
    torch.testing.assert_close(obs_h["heading"], torch.stack([yaw2.cos(), yaw2.sin()], -1))
    # the goal and the goal turned 180 deg: headings opposite (the images nearly mirror)
    env = head.unwrapped if hasattr(head, "unwrapped") else head
    goal = env.goal_cmd.clone()
    flipped = goal.clone()
    flipped[:, 2] = 0.0
    ids = torch.arange(4)
    env.scene.reset(ids, torch.cat([goal[:2], flipped[2:]]))
    h = env._get_observations(None)["heading"]
    assert float(h[:2, 0].max()) < -0.99 and float(h[2:, 0].min()) > 0.99


def test_us_memory_observes_the_image_and_pose_memory_lag_steps_back():
    """``us_memory``: channel 0 and heading[:2] are ``us_heading``'s; channel 1, heading[2:]
    and the motion are the image (8 bits), heading and frontal-plane displacement of the
    reached probe ``memory_lag`` steps earlier, or the episode's first until it is that old,
    across in-step autoresets and partial resets."""
    lag, n = 3, 2
    env = NavigationEnv(n, obs_mode="us_memory", memory_lag=lag, episode_length=7, **FAST)
    assert env.observation_space.contains({k: v.numpy() for k, v in env.reset(seed=1)[0].items()})

    def current(obs):
        x, z, yaw, _ = env.scene.measured_command()
        return obs["image"][:, 0].clone(), torch.stack([x, z, yaw], -1)

    obs, _ = env.reset(seed=1)
    history = [current(obs)]  # per step since the last reset: (image, pose)
    gen = torch.Generator().manual_seed(0)
    for step in range(1, 16):
        obs, *_ = env.step(torch.rand(n, 3, generator=gen) * 4 - 2)
        if step == 10:  # a partial reset restarts env 1's memory only
            obs, _ = env.reset(options={"reset_mask": torch.tensor([False, True])})
        history.append(current(obs))
        t = env.episode_length_buf
        for i in range(n):
            then = len(history) - 1 - min(int(t[i]), lag)
            image_then, pose_then = history[then][0][i], history[then][1][i]
            image_now, pose_now = history[-1][0][i], history[-1][1][i]
            assert torch.equal(obs["image"][i, 0], image_now)
            want = (image_then.clamp(0, 1) * 255).round() / 255
            torch.testing.assert_close(obs["image"][i, 1], want, rtol=0, atol=1e-6)
            heading = torch.stack([pose_now[2].cos(), pose_now[2].sin(),
                                   pose_then[2].cos(), pose_then[2].sin()])  # fmt: skip
            torch.testing.assert_close(obs["heading"][i], heading)
            torch.testing.assert_close(obs["motion"][i], pose_now[:2] - pose_then[:2])
        if bool((t == 0).all()):  # the in-step autoreset at step 7 restarts every history
            history = history[-1:]
        elif bool((t == 0).any()):  # after the partial reset the envs' histories differ
            break
    assert step == 10  # checked: steps 1-10, the autoreset at 7 and the partial reset


def test_us_memory_is_read_the_same_when_observed_twice():
    """Observing a step twice (the final observation of an ended episode is taken before the
    autoreset) neither shifts the memory nor changes what is read."""
    env = NavigationEnv(2, obs_mode="us_memory", memory_lag=2, **FAST)
    env.reset(seed=0)
    for _ in range(4):
        obs, *_ = env.step(torch.ones(2, 3))
        again = env._get_observations(None)
        for k in obs:
            assert torch.equal(obs[k], again[k]), k
    assert float(obs["motion"].norm(dim=1).min()) > 1e-3  # the probes moved in the window


def test_us_scan_adds_the_image_and_pose_where_the_probe_was_most_caudal():
    """``us_scan``: ``us_memory``'s entries first, then the image (8 bits), heading and
    displacement from the reached pose with the lowest z since the episode began (the first
    such pose on ties), across in-step autoresets and partial resets."""
    lag, n = 2, 2
    env = NavigationEnv(n, obs_mode="us_scan", memory_lag=lag, episode_length=9, **FAST)
    memory = NavigationEnv(n, obs_mode="us_memory", memory_lag=lag, episode_length=9, **FAST)
    obs, _ = env.reset(seed=1)
    assert env.observation_space.contains({k: v.numpy() for k, v in obs.items()})
    ref, _ = memory.reset(seed=1)

    def current(obs):
        x, z, yaw, _ = env.scene.measured_command()
        return obs["image"][:, 0].clone(), torch.stack([x, z, yaw], -1)

    history = [current(obs)]
    starts = [0, 0]  # index in history where each env's episode began
    gen = torch.Generator().manual_seed(0)
    lowered = 0
    for step in range(1, 14):
        # mostly along the spine, both ways: the caudal end moves, then stays
        action = torch.rand(n, 3, generator=gen) * 4 - 2
        obs, *_ = env.step(action)
        ref, *_ = memory.step(action)
        if step == 11:  # a partial reset restarts env 1's scan only
            obs, _ = env.reset(options={"reset_mask": torch.tensor([False, True])})
            ref, _ = memory.reset(options={"reset_mask": torch.tensor([False, True])})
        history.append(current(obs))
        t = env.episode_length_buf
        for i in range(n):
            if int(t[i]) == 0:
                starts[i] = len(history) - 1
            for key, width in (("image", 2), ("heading", 4), ("motion", 2)):
                torch.testing.assert_close(obs[key][i, :width], ref[key][i])
            zs = [float(h[1][i, 1]) for h in history[starts[i] :]]
            low = starts[i] + zs.index(min(zs))
            lowered += low != starts[i] and low == len(history) - 1
            image_low, pose_low = history[low][0][i], history[low][1][i]
            pose_now = history[-1][1][i]
            want = (image_low.clamp(0, 1) * 255).round() / 255
            torch.testing.assert_close(obs["image"][i, 2], want, rtol=0, atol=1e-6)
            heading = torch.stack([pose_low[2].cos(), pose_low[2].sin()])
            torch.testing.assert_close(obs["heading"][i, 4:], heading)
            torch.testing.assert_close(obs["motion"][i, 2:], pose_now[:2] - pose_low[:2])
            assert float(obs["motion"][i, 3]) >= 0.0  # nowhere lower than the caudal end
    assert lowered >= 2  # the caudal end moved during episodes, not only at their starts
    again = env._get_observations(None)  # observed twice: nothing moves
    for k in obs:
        assert torch.equal(obs[k], again[k]), k


@pytest.mark.parametrize("lag", [0, -3, 2.5])
def test_memory_lag_must_be_a_positive_whole_number_of_steps(lag):
    with pytest.raises(ValueError, match="memory_lag"):
        NavigationEnv(1, obs_mode="us_memory", memory_lag=lag, **FAST)


def test_probe_tilt_is_the_vertical_seen_across_and_along_the_image():
    """(y_P . x_U, y_P . y_U): zero for a beam along +y_P; sin(theta) across the image for a
    beam turned theta about the image's elevation axis, and along it for the other axis."""
    x_u, y_u, z_u = torch.tensor([-1.0, 0, 0]), torch.tensor([0, 0, 1.0]), torch.tensor([0, 1.0, 0])
    upright = torch.stack([x_u, y_u, z_u], -1)[None]
    torch.testing.assert_close(probe_tilt(upright), torch.zeros(1, 2))
    th = 0.3
    c, s = math.cos(th), math.sin(th)
    across = torch.stack([x_u * c + z_u * s, y_u, z_u * c - x_u * s], -1)[None]
    along = torch.stack([x_u, y_u * c + z_u * s, z_u * c - y_u * s], -1)[None]
    torch.testing.assert_close(probe_tilt(across), torch.tensor([[s, 0.0]]))
    torch.testing.assert_close(probe_tilt(along), torch.tensor([[0.0, s]]))


@pytest.mark.parametrize("mode", ["us_heading", "us_scan"])
def test_observe_tilt_adds_the_reached_probes_tilt_from_the_skin_normal(mode):
    """``observe_tilt``: the Dict gains ``tilt`` = ``probe_tilt`` of the reached pose, the rest
    unchanged; with the beam along the skin's inward normal n, |tilt|^2 = 1 - n_y^2."""
    plain, tilted = _env(4, obs_mode=mode), _env(4, obs_mode=mode, observe_tilt=True)
    obs_p, _ = plain.reset(seed=3)
    obs_t, _ = tilted.reset(seed=3)
    assert set(obs_t) == set(obs_p) | {"tilt"}
    assert tilted.observation_space.contains({k: v.numpy() for k, v in obs_t.items()})
    for k in obs_p:
        assert torch.equal(obs_t[k], obs_p[k]), k
    env = tilted.unwrapped if hasattr(tilted, "unwrapped") else tilted
    obs_t, *_ = tilted.step(torch.ones(4, 3))
    rot = env.scene.probe_rot
    torch.testing.assert_close(obs_t["tilt"], rot[:, 1, :2].float())
    x, z, _, tilt = env.scene.measured_command()
    n = env.scene.skin.normal(x, z, env.scene.patient_index)
    assert float(tilt.abs().max()) < 0.05  # the arm holds the beam near the normal
    torch.testing.assert_close(
        obs_t["tilt"].pow(2).sum(-1), 1 - n[:, 1].float() ** 2, atol=0.02, rtol=0
    )
    assert float(obs_t["tilt"].abs().max()) > 0.01  # the back is not flat: something to see


def test_observe_tilt_needs_a_dict_observation():
    with pytest.raises(ValueError, match="observe_tilt.*us_scan"):
        NavigationEnv(1, obs_mode="us", observe_tilt=True, **FAST)


def test_measured_command_is_computed_once_per_pose_and_stays_fresh(monkeypatch):
    """A step reads the reached pose's command several times (yaw lead, info, heading,
    metrics) but computes it once; after steps, partial resets and direct pose writes the
    kept value equals a fresh computation from the pose."""
    env = NavigationEnv(4, obs_mode="us_heading", episode_length=3, **FAST)
    sc = env.scene
    env.reset(seed=0)
    calls = []
    original = type(sc.skin).command_from_pose

    def counted(self, *args, **kwargs):
        calls.append(1)
        return original(self, *args, **kwargs)

    monkeypatch.setattr(type(sc.skin), "command_from_pose", counted)

    def fresh(ids=slice(None)):
        return original(sc.skin, sc.probe_pos[ids], sc.probe_rot[ids], sc.patient_index[ids])

    gen = torch.Generator().manual_seed(0)
    for step in range(7):  # episodes end at steps 3 and 6: in-step autoresets
        calls.clear()
        _, _, _, trunc, info = env.step(torch.rand(4, 3, generator=gen) * 2 - 1)
        # one computation after the arm moved, one more after an autoreset moved the probes
        assert len(calls) == 1 + bool(trunc.any()), (step, len(calls))
        for got, want in zip(sc.measured_command(), fresh(), strict=True):
            assert torch.equal(got, want)
        ids = torch.tensor([1, 3])
        for got, want in zip(sc.measured_command(ids), fresh(ids), strict=True):
            assert torch.equal(got, want)
    env.reset(options={"reset_mask": torch.tensor([False, True, False, False])})
    assert torch.equal(torch.stack(sc.measured_command(), -1), torch.stack(fresh(), -1))
    # a write to the pose, in place or by assignment, is seen
    sc.probe_pos[2, 0] += 0.01
    assert torch.equal(sc.measured_command()[0], fresh()[0])
    sc.probe_rot = sc.probe_rot.flip(0).clone()
    assert torch.equal(sc.measured_command()[2], fresh()[2])
    # the caller owns what it gets
    sc.measured_command()[0].zero_()
    assert torch.equal(sc.measured_command()[0], fresh()[0])


# ----------------------------------------------------------------- the goal {G}


def _beam_miss_mm(env) -> np.ndarray:
    """How far (mm) each env's goal beam (from {G}'s origin along its z axis) passes from the
    target vertebra's body centroid."""
    c = env.scene.target_centres.double()
    g, beam = env.goal_pos.double(), env.goal_rot[:, :, 2].double()
    d = c - g
    return ((d - (d * beam).sum(-1, keepdim=True) * beam).norm(dim=-1) * 1e3).numpy()


@pytest.fixture(scope="module")
def rolled_phantoms(tmp_path_factory):
    """Folders of seed-0 phantoms at 2 mm: rolled on the table with the spine (no rotation
    within the trunk), and rolled with the spine also rotated in the trunk and the vertebrae
    axially rotated."""
    from sonogym.anatomy import PhantomParams, make_phantom
    from sonogym.anatomy.totalseg import save_totalsegmentator

    out = {}
    for name, kw in {
        "rolled": dict(trunk_roll=0.12, spine_rotation=0.0, axial_rotation=0.0),
        "rolled-rotated": dict(trunk_roll=0.12, spine_rotation=0.08, axial_rotation=0.05),
    }.items():
        p = make_phantom(0, PhantomParams(spacing=0.002, **kw))
        folder = save_totalsegmentator(p, tmp_path_factory.mktemp(name))
        out[name] = (str(folder), p.meta["vertebrae"]["L4"])
    return out


@pytest.mark.parametrize("name", ["rolled", "rolled-rotated"])
def test_goal_beam_passes_through_the_l4_centroid(rolled_phantoms, name):
    folder, _ = rolled_phantoms[name]
    env = _env(1, patients=(folder,), obs_mode="state", robot=None)
    assert _beam_miss_mm(env).max() < 1.0
    # the goal is the transverse pose on the skin
    skin_y = env.scene.skin.height(env.goal_pos[:, 0], env.goal_pos[:, 2], env.scene.patient_index)
    assert torch.allclose(env.goal_pos[:, 1], skin_y, atol=1e-6)
    assert torch.allclose(env.goal_cmd[:, 2], torch.tensor(math.pi))


def test_goal_lies_on_the_midsagittal_plane_of_a_spine_rolled_with_the_trunk(rolled_phantoms):
    """A patient rolled on the table (spine and trunk together): {G} lies on L4's midsagittal
    plane (the generator's own frame), where the old goal straight above the centroid lay
    ~12 mm off it."""
    folder, truth = rolled_phantoms["rolled"]
    env = _env(1, patients=(folder,), obs_mode="state", robot=None)
    lateral = torch.tensor(truth["rotation"], dtype=torch.float64)[:, 0]
    centre = torch.tensor(truth["centre_m"], dtype=torch.float64)
    off = float((env.goal_pos[0].double() - centre) @ lateral) * 1e3
    assert abs(off) < 1.0
    above = env.scene.skin.point(centre[0:1], centre[2:3]).double()[0]
    assert abs(float((above - centre) @ lateral) * 1e3) > 5.0  # the old goal: off the plane


def test_goal_beam_passes_through_the_real_l4_centroid():
    subject = str(Path(__file__).resolve().parents[1] / "data" / "totalsegmentator_example")
    env = _env(2, patients=(subject, 0), obs_mode="state", robot=None)
    assert _beam_miss_mm(env).max() < 1.0
