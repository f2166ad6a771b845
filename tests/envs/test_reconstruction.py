import math

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env

import sonogym  # noqa: F401
from sonogym.envs.reconstruction import (
    ReconstructionEnv,
    heuristic_raster,
    raster_reference,
    raster_waypoints,
    reconstruction_objective,
    reconstruction_reward,
    reference_surface,
)

FAST = dict(patients=(0,), phantom_spacing=0.002)
#: Coverage the heuristic raster reaches on the 2 mm seed-0 phantom, ideal probe, seed 0
#: (measured 0.88, docs/envs.md); asserted with a margin.
HEURISTIC_COVERAGE = 0.72


def _env(n, **kw):
    return gym.make_vec("SonoGym/Reconstruction-v0", num_envs=n, **{**FAST, "robot": None, **kw})


def _random(n, g):
    return torch.rand(n, 4, generator=g) * 4 - 2


def test_make_vec_gives_the_native_batched_env():
    env = _env(3)
    assert isinstance(env, ReconstructionEnv)
    assert env.num_envs == 3 and env.single_action_space.shape == (4,)
    assert env.metadata["autoreset_mode"] == gym.vector.AutoresetMode.SAME_STEP


def test_single_env_passes_gymnasium_checker():
    env = gym.make("SonoGym/Reconstruction-v0", **FAST, robot=None)
    check_env(env.unwrapped, skip_render_check=True)


def test_observation_matches_its_declared_space():
    env = _env(2)
    obs, _ = env.reset(seed=0)
    assert set(obs) == {"reconstruction", "path_length"}
    assert obs["reconstruction"].shape == (2, 40, 40, 40)
    assert obs["reconstruction"].dtype == obs["path_length"].dtype == torch.float32
    assert obs["path_length"].shape == (2, 1)
    assert float(obs["reconstruction"].abs().sum()) == 0.0  # nothing scanned yet
    g = torch.Generator().manual_seed(0)
    for _ in range(5):
        obs, *_ = env.step(_random(2, g))
    np_obs = {k: v.numpy() for k, v in obs.items()}
    assert env.observation_space.contains(np_obs)
    assert set(torch.unique(obs["reconstruction"]).tolist()) == {0.0, 1.0}
    assert (obs["path_length"] > 0.005).all()  # metres
    st = _env(2, obs_mode="state")
    o, info = st.reset(seed=0)
    assert o.shape == (2, 6) and torch.equal(o, info["state"])


def test_probe_frame_observation_is_v_resampled_by_hand():
    env = _env(2, missing_rate=0.0)
    env.reset(seed=3)
    g = torch.Generator().manual_seed(1)
    for _ in range(30):
        obs, _, _, _, info = env.step(_random(2, g))
    rec = obs["reconstruction"]
    assert rec.sum() > 20
    size, vox = 40, 0.003
    for e in range(2):
        pos = env.scene.probe_pos[e].double()
        rot = env.scene.probe_rot[e].double()
        corner = env._corner[env.scene.patient_index[e]]
        ones = torch.nonzero(rec[e])[:100]
        rnd = torch.randint(0, size, (300, 3), generator=g)
        for i, j, k in torch.cat([ones, rnd]).tolist():
            u = torch.tensor([(i - 19.5) * vox, (j - 19.5) * vox, (k + 0.5) * vox])
            p = pos + rot @ u.double()
            c = torch.floor((p - corner) / vox).long()
            inside = bool(((c >= 0) & (c < size)).all())
            want = float(env.volume[e][tuple(c.tolist())]) if inside else 0.0
            assert rec[e, i, j, k].item() == want, (e, i, j, k)
    # and the volume holds the surface: its voxels lie where the sensor reported points
    assert env.volume.sum() >= info["covered_voxels"].sum() > 0


def test_rewards_sum_to_the_objective_computed_by_hand():
    n, steps = 4, 60
    env = _env(n, episode_length=steps)
    _, info = env.reset(seed=2)
    g = torch.Generator().manual_seed(4)
    scale = torch.tensor([3.0, 3.0, 0.1, 0.1], dtype=torch.float64)  # mm, mm, rad, rad
    limit = torch.tensor([6.0, 6.0, 0.2, 0.2], dtype=torch.float64)
    yaw_lo, yaw_hi = math.pi - 2.5, math.pi + 2.5
    total = torch.zeros(n, dtype=torch.float64)
    trans = torch.zeros(n, dtype=torch.float64)
    rot = torch.zeros(n, dtype=torch.float64)
    for t in range(steps):
        a = _random(n, g)
        cmd0 = env.command.clone().double()
        _, r, _, _, info = env.step(a)
        total += r.double()
        d = torch.maximum(torch.minimum(a.double() * scale, limit), -limit)
        trans += d[:, :2].abs().sum(1)  # mm, as commanded
        dyaw = (cmd0[:, 2] + d[:, 2]).clamp(yaw_lo, yaw_hi) - cmd0[:, 2]
        dtilt = (cmd0[:, 3] + d[:, 3]).clamp(-0.4, 0.4) - cmd0[:, 3]
        rot += dyaw.abs() + dtilt.abs()  # rad, as applied
        f = info["covered_voxels"].double() - 0.01 * trans - 1.0 * rot
        assert torch.allclose(info["objective"], f, atol=1e-5, rtol=0)
        assert torch.allclose(total, f, atol=2e-4, rtol=0)  # sum of float32 rewards
        if t < steps - 1:
            m = (env.volume & env._reference[env.scene.patient_index]).flatten(1).sum(1)
            assert torch.equal(info["covered_voxels"], m)
    # at the end: the return is F(tau) - F(empty), F(empty) = 0
    fin = info["final_info"]
    assert torch.allclose(fin["return"].double(), f, atol=2e-4, rtol=0)
    assert torch.allclose(fin["total_rotation_deg"].double(), torch.rad2deg(rot), atol=1e-3, rtol=0)
    want = reconstruction_objective(info["covered_voxels"], trans, rot)
    assert torch.allclose(want, info["objective"], atol=1e-5, rtol=0)
    assert (info["covered_voxels"] > 0).all()
    # after the autoreset: a fresh episode with F = 0 and an empty volume
    assert (env.objective == 0).all() and not env.volume.any()


def test_path_and_angle_accounting_of_a_scripted_episode():
    # missing_rate 1: nothing is ever reconstructed, so every reward is a pure cost
    acts = torch.tensor(
        [
            [1.0, 0.0, 0.0, 0.0],  # 3 mm along x_U
            [0.0, -3.0, 0.0, 0.0],  # clipped to -6 mm along y_U
            [1.0, 1.0, 0.0, 0.0],  # 3 + 3 mm (L1), 4.243 mm (L2)
            [0.0, 0.0, 1.0, 0.0],  # yaw +0.1 rad
            [0.0, 0.0, -2.5, 2.0],  # yaw -0.2 (clipped), tilt +0.2
            [0.0, 0.0, 0.0, 2.0],  # tilt +0.2 -> 0.4
            [0.0, 0.0, 0.0, 2.0],  # tilt clamped at 0.4: applied 0, costs 0
        ]
    )
    env = _env(1, episode_length=len(acts), missing_rate=1.0, robot=None)  # reached = command
    _, info = env.reset(seed=0)
    rewards, xz = [], [info["command"][0, :2]]
    for a in acts:
        _, r, _, _, info = env.step(a[None])
        rewards.append(r.item())
        xz.append(env.command[0, :2].clone() if "final_info" not in info else xz[-1])
    want_r = [-0.03, -0.06, -0.06, -0.1, -0.2 - 0.2, -0.2, 0.0]
    np.testing.assert_allclose(rewards, want_r, atol=1e-6)
    fin = info["final_info"]
    # the path is the motion that happened on the frontal plane: the 3 + 6 + 4.24 mm steps on
    # the skin, projected (the back slopes a little)
    moved = sum(float((b - a).norm()) for a, b in zip(xz[:-1], xz[1:], strict=True)) * 1e3
    assert fin["trajectory_length_mm"].item() == pytest.approx(moved, abs=1e-3)
    assert moved == pytest.approx(3 + 6 + math.sqrt(18), rel=0.03)
    assert fin["total_rotation_deg"].item() == pytest.approx(math.degrees(0.7), abs=1e-4)
    assert fin["coverage"].item() == 0.0
    assert fin["return"].item() == pytest.approx(sum(want_r), abs=1e-5)
    assert info["objective"].item() == pytest.approx(sum(want_r), abs=1e-6)


def test_path_counts_the_motion_that_happened_not_blocked_commands():
    # 300 steps pushing +x at 6 mm per step from the centre: the workspace clamp (60 mm) stops
    # the command after ~10 steps; the commanded steps would sum to 1,800 mm
    env = _env(1, episode_length=300, missing_rate=1.0)
    env.reset(seed=0)
    push = torch.tensor([[2.0, 0.0, 0.0, 0.0]])
    for _ in range(300):
        obs, _, _, _, info = env.step(push)
    length = info["final_info"]["trajectory_length_mm"].item()
    start_to_edge = 60 + 15  # at most: the start lies within 15 mm of the centre
    assert 45 <= length <= start_to_edge + 10, length
    assert info["final_obs"]["path_length"][0, 0].item() == pytest.approx(length * 1e-3, rel=1e-5)


def test_action_scaling_moves_the_command_in_si_units():
    env = _env(2)
    env.reset(seed=0)
    before = env.command.clone()
    m = env.tangent_map()
    env.step(torch.tensor([[1.0, 0.0, 1.0, 1.0], [0.0, -5.0, -5.0, -5.0]]))
    d = env.command - before
    assert torch.allclose(d[0, :2], 0.003 * m[0, :, 0], atol=1e-6)  # 3 mm along x_U
    assert torch.allclose(d[1, :2], -0.006 * m[1, :, 1], atol=1e-6)  # clipped to 6 mm
    assert torch.allclose(m.det().abs(), torch.ones(2), atol=0.1)  # near-flat skin here
    assert d[0, 2].item() == pytest.approx(0.1) and d[0, 3].item() == pytest.approx(0.1)
    assert d[1, 2].item() == pytest.approx(-0.2) and d[1, 3].item() == pytest.approx(-0.2)
    # the reached (ideal) probe is tilted about x_U by the commanded tilt
    _, _, _, tilt = env.scene.measured_command()
    assert torch.allclose(tilt, env.command[:, 3], atol=1e-5)


def test_missing_rate_of_sensed_points_is_02():
    n = 24  # ~22 000 visible points over 40 steps on the seed-0 phantom
    env = _env(n)
    _, info = env.reset(seed=0)
    vis = kept = 0
    g = torch.Generator().manual_seed(0)
    for _ in range(40):  # small random moves over the vertebra
        _, _, _, _, info = env.step(_random(n, g) * 0.3)
        vis += int(info["visible_points"].sum())
        kept += int(info["sensed_points"].sum())
    assert vis > 15000  # std of the estimate < 0.0033
    assert 1 - kept / vis == pytest.approx(0.2, abs=0.02)


def test_heuristic_coverage_is_monotone_bounded_and_beats_random():
    n = 4
    env = _env(n)
    _, info = env.reset(seed=0)
    prev = torch.zeros(n)
    final = None
    for _ in range(env.episode_length):
        _, r, _, _, info = env.step(heuristic_raster(env, info))
        if "final_info" in info:
            final = info["final_info"]
            break
        cov = info["coverage"]
        assert (cov >= prev).all() and (cov <= 1.0).all()
        prev = cov
    cov = final["coverage"]
    assert (cov >= HEURISTIC_COVERAGE).all() and (cov <= 1.0).all(), cov
    # the random policy pays more for less: the heuristic's return is higher
    _, info = env.reset(seed=0)
    g = torch.Generator().manual_seed(1)
    for _ in range(env.episode_length):
        _, _, _, _, info = env.step(_random(n, g))
    assert final["return"].mean() > info["final_info"]["return"].mean() + 30


def test_reference_surface_is_the_straight_dorsal_view():
    from sonogym.envs.patients import resolve_patients

    p = resolve_patients((0,), 0.002)[0]
    env = _env(1)
    r = env._reference[0]
    corner = env._corner[0].numpy()
    assert 100 < int(r.sum()) == int(env.reference_voxels[0])
    # R is the first-bone layer: each R voxel's column has no R voxel behind it further than
    # a few voxels (a surface, not a solid), and its voxels hold target voxels
    lab = p.labels
    idx = torch.nonzero(r)
    centres = torch.tensor(corner) + (idx.double() + 0.5) * 0.003
    vox = torch.round((centres - torch.tensor(p.origin)) / torch.tensor(p.spacing)).long()
    near = []
    for v in vox:
        sl = lab[v[0] - 1 : v[0] + 2, v[1] - 1 : v[1] + 2, v[2] - 1 : v[2] + 2]
        near.append(bool((sl == 28).any()))
    assert np.mean(near) > 0.95
    # dropping the depth limit adds deeper (body) surface; zero depth keeps nothing
    deep = reference_surface(p, 28, corner, 0.003, 40, max_depth=1.0)
    assert (deep | r).sum() == deep.sum() and deep.sum() > r.sum()
    assert reference_surface(p, 28, corner, 0.003, 40, max_depth=0.0).sum() == 0


def test_reward_of_a_known_step():
    r = reconstruction_reward(
        torch.tensor([5]), torch.tensor([[3.0, -6.0]]), torch.tensor([[0.1, -0.2]])
    )
    assert r.item() == pytest.approx(5 - 0.01 * 9 - 1.0 * 0.3)
    f = reconstruction_objective(torch.tensor([10]), torch.tensor([100.0]), torch.tensor([2.0]))
    assert f.item() == pytest.approx(10 - 1 - 2)


def test_raster_is_timed_to_the_episode():
    wps = raster_waypoints()
    assert wps.shape == (12, 4)
    t = torch.tensor([0, 10, 15, 300, 400])
    ref = raster_reference(t, 300, wps)
    assert torch.allclose(ref[:3], wps[0].expand(3, 4))
    assert torch.allclose(ref[3:], wps[-1].expand(2, 4))
    mid = raster_reference(torch.arange(300), 300, wps)
    step = (mid[1:, :2] - mid[:-1, :2]).norm(dim=-1)
    assert step.max() < 0.006  # within the per-step translation limit


def test_same_seed_same_episode_bit_for_bit_with_the_arm():
    def run():
        env = gym.make_vec("SonoGym/Reconstruction-v0", num_envs=2, **FAST)
        obs, info = env.reset(seed=7)
        out = [obs["reconstruction"], info["state"]]
        g = torch.Generator().manual_seed(3)
        sensed = 0
        for _ in range(4):
            obs, r, _, _, info = env.step(_random(2, g))
            out += [obs["reconstruction"], obs["path_length"], r, info["command"]]
            sensed += int(info["sensed_points"].sum())
            assert info["reachable"].all()
        return out, sensed, env

    (a, sensed, env), (b, _, _) = run(), run()
    assert all(torch.equal(x, y) for x, y in zip(a, b, strict=True))
    assert sensed > 0

    # the arm lags behind fast commands, then settles onto them
    def lag():
        x, z, _, tilt = env.scene.measured_command()
        c = env.command
        return torch.stack([x - c[:, 0], z - c[:, 1]], -1).norm(dim=-1), (tilt - c[:, 3]).abs()

    assert (lag()[0] < 0.015).all()
    for _ in range(10):
        env.step(torch.zeros(2, 4))
    pos_lag, tilt_lag = lag()
    assert (pos_lag < 0.002).all() and (tilt_lag < 0.02).all()


def test_partial_reset_clears_only_the_reset_envs():
    env = _env(3, missing_rate=0.0)
    env.reset(seed=0)
    for _ in range(5):
        obs, _, _, _, info = env.step(torch.zeros(3, 4))
    assert (info["covered_voxels"] > 0).all()
    mask = torch.tensor([True, False, True])
    obs2, info2 = env.reset(options={"reset_mask": mask})
    assert torch.equal(obs2["reconstruction"][1], obs["reconstruction"][1])
    assert (info2["covered_voxels"][mask] == 0).all() and not env.volume[mask].any()
    assert info2["covered_voxels"][1] == info["covered_voxels"][1]
    assert (obs2["path_length"][mask] == 0).all()


def test_bad_options_raise():
    with pytest.raises(ValueError, match="obs_mode"):
        _env(1, obs_mode="us")
    with pytest.raises(ValueError, match="missing_rate"):
        _env(1, missing_rate=1.2)
    with pytest.raises(ValueError, match="target_vertebra"):
        _env(1, target_vertebra="L9")  # not a vertebra
    with pytest.raises(TypeError, match="valid options"):
        _env(1, tilt=0.3)
    env = _env(2)
    env.reset(seed=0)
    with pytest.raises(ValueError, match="shape"):
        env.step(torch.zeros(2, 3))


def test_demo_runs_the_heuristic_and_draws_the_reconstruction():
    from sonogym.envs.registry import get_task
    from sonogym.tasks.demo import task_demo

    task = get_task("reconstruction")
    env = _env(2, missing_rate=0.0)
    _, info = env.reset(seed=0)
    for _ in range(3):
        obs, _, _, _, info = env.step(task.expert(env, info))
    img = task_demo("reconstruction").image(obs)
    assert img.shape == (200, 200) and 0 < float(img.max()) <= 1.0
    assert env.render().shape == (200, 200, 3)
