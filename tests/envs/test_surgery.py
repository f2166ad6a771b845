import math

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env

import sonogym  # noqa: F401
from sonogym.anatomy.labels import VERTEBRA_IDS
from sonogym.envs.surgery import (
    DRILL,
    FREE,
    UNSAFE,
    SurgeryEnv,
    clamp_to_ball,
    corridor_damping,
    distance_to_safe_set,
    state_observation,
    surgery_expert,
    surgery_regions,
    surgery_reward,
)
from sonogym.geometry import axis_angle_from_matrix, matrix_from_axis_angle, matrix_from_quat

FAST = dict(patients=(0,), phantom_spacing=0.002)
L = 0.05  # m, skin distance l
W4, W5, W6 = 30.0, 5.0, 300.0


def _env(n, **kw):
    return gym.make_vec("SonoGym/Surgery-v0", num_envs=n, **{**FAST, **kw})


def _run_expert(env, info, steps):
    final = None
    for _ in range(steps):
        a = surgery_expert(info["state"], info["radius"])
        _, _, _, _, info = env.step(a)
        final = info.get("final_info", final)
    return final, info


# ----------------------------------------------------------------------------- pure functions


def test_regions_on_hand_made_points():
    hw = torch.full((8,), 0.0055)  # d/2 = r + 2 mm with r = 3.5 mm
    p = torch.tensor(
        [
            [0.0, 0.0, -0.10],  # far above: free
            [0.08, 0.0, -0.051],  # anywhere with p_z <= -l: free, however lateral
            [0.0, 0.0, -0.05],  # p_l itself: free (p_z = -l)
            [0.0, 0.0, -0.02],  # on the axis inside the corridor: drill
            [0.0038, 0.0038, -0.001],  # lateral 5.37 mm < 5.5 mm: drill
            [0.0, 0.0056, -0.02],  # just outside the cylinder: unsafe
            [0.0, 0.0, 0.001],  # past the target: unsafe
            [0.02, 0.0, -0.049],  # beside the corridor below p_l's plane: unsafe
        ]
    )
    want = [FREE, FREE, FREE, DRILL, DRILL, UNSAFE, UNSAFE, UNSAFE]
    assert surgery_regions(p, hw, L).tolist() == want


P = 0.3  # unsafe_penalty (reward per unsafe step)


def _reward(p0, t0, p1, t1, hw=0.0055, k=0.0, cap=math.inf):
    out = surgery_reward(
        torch.tensor([p0], dtype=torch.float64),
        torch.tensor([t0], dtype=torch.float64),
        torch.tensor([p1], dtype=torch.float64),
        torch.tensor([t1], dtype=torch.float64),
        torch.tensor([hw], dtype=torch.float64),
        L,
        W4,
        W5,
        W6,
        P,
        k,
        cap,
    )
    return [o[0] for o in out]


def test_reward_is_the_papers_formula_within_each_safe_region():
    # C_free -> C_free: w4 (|p_t - p_l| - |p_t+1 - p_l|) + w5 (theta_t - theta_t+1), per m/rad
    p0, p1 = [0.03, 0.01, -0.12], [0.02, 0.0, -0.10]
    pl = np.array([0, 0, -L])
    want = W4 * (np.linalg.norm(np.array(p0) - pl) - np.linalg.norm(np.array(p1) - pl))
    want += W5 * (0.3 - 0.25)
    r, c, reg = _reward(p0, 0.3, p1, 0.25)
    assert r.item() == pytest.approx(want, abs=1e-9) and c.item() == 0 and reg.item() == FREE
    # C_drill, deepening along the corridor: w6 (|p_t| - |p_t+1|) + w5 (...)
    p0, p1 = [0.001, 0.0, -0.03], [0.0005, 0.0, -0.02]
    want = W6 * (np.linalg.norm(p0) - np.linalg.norm(p1)) + W5 * (0.05 - 0.02)
    r, c, reg = _reward(p0, 0.05, p1, 0.02)
    assert r.item() == pytest.approx(want, abs=1e-9) and c.item() == 0 and reg.item() == DRILL
    # C_free -> C_drill through p_l: the two formulas meet there (Phi = 0 at p_l, theta 0)
    r, *_ = _reward([0, 0, -0.06], 0.0, [0, 0, -0.04], 0.0)
    assert r.item() == pytest.approx(W4 * 0.01 + W6 * 0.01)


def test_backing_out_of_the_corridor_gives_back_what_going_in_earned():
    r_in, *_ = _reward([0, 0, -0.03], 0.0, [0, 0, -0.02], 0.0)
    r_out, *_ = _reward([0, 0, -0.02], 0.0, [0, 0, -0.03], 0.0)
    assert r_in.item() == pytest.approx(W6 * 0.01) and r_out.item() == pytest.approx(-W6 * 0.01)


def test_leaving_the_safe_set_costs_what_it_earned_plus_the_penalty():
    # out of the corridor at 20 mm before the target: everything the insertion earned is lost
    p0, p1 = np.array([0, 0, -0.02]), np.array([0.01, 0, -0.02])
    r, c, reg = _reward(p0.tolist(), 0.0, p1.tolist(), 0.0)
    pl = np.array([0, 0, -L])
    phi0 = W6 * (L - np.linalg.norm(p0))  # 9: the insertion so far
    phi1 = -W4 * np.linalg.norm(p1 - pl)
    assert c.item() == 1.0 and reg.item() == UNSAFE
    assert r.item() == pytest.approx(phi1 - phi0 - P)
    assert r.item() < -phi0
    # within the unsafe region: the C_free formula's shaping toward p_l, minus the penalty
    r, c, _ = _reward([0.03, 0, -0.04], 0.0, [0.02, 0, -0.04], 0.0)
    want = W4 * (np.hypot(0.03, 0.01) - np.hypot(0.02, 0.01)) - P
    assert c.item() == 1.0 and r.item() == pytest.approx(want)
    # back into C_free: the same formula, no penalty
    r, c, reg = _reward([0.02, 0, -0.045], 0.0, [0.02, 0, -0.055], 0.0)
    assert c.item() == 0 and reg.item() == FREE and r.item() == pytest.approx(0.0, abs=1e-12)


def test_distance_to_the_safe_set_on_hand_made_points():
    hw = torch.full((6,), 0.003)
    p = torch.tensor(
        [
            [0.010, 0.0, -0.020],  # beside the corridor: 7 mm to its wall (30 mm to the plane)
            [0.001, 0.0, 0.004],  # past the target on the axis: 4 mm
            [0.008, 0.0, 0.003],  # past the target and aside: hypot(5, 3) mm
            [0.050, 0.0, -0.045],  # far aside just below p_l's plane: 5 mm up to the plane
            [0.0, 0.0, -0.060],  # C_free
            [0.002, 0.0, -0.010],  # C_drill
        ]
    )
    want = [7.0, 4.0, float(np.hypot(5.0, 3.0)), 5.0, 0.0, 0.0]
    got = distance_to_safe_set(p, hw, L) * 1e3
    assert got.tolist() == pytest.approx(want, abs=1e-4)


def test_distance_penalty_makes_sliding_into_the_corridor_at_depth_cost_more_than_the_entrance():
    """A PPO state seed cut the corner: it dove beside the corridor below p_l's plane and slid
    in sideways at depth (unsafe a median 10 mm aside, 27 mm before the target), which the
    flat penalty charges only 0.3 per step. With unsafe_distance_penalty = w6 the dive earns
    less than going through p_l, while a tip 0.5 mm outside near the entrance costs barely
    more than before, and the cap bounds any one step's cost."""

    def ret(path, k):
        steps = zip(path[:-1], path[1:], strict=True)
        return sum(_reward(list(a), 0.0, list(b), 0.0, k=k)[0].item() for a, b in steps)

    start = [0.04, 0.0, -0.06]
    end = [0, 0, -0.02]
    proper = [np.array(start), *_segment(start, [0, 0, -L], 6), *_segment([0, 0, -L], end, 5)]
    aside = [0.015, 0, -0.025]  # 9.5 mm beside the corridor wall, 25 mm before the target
    dive = [np.array(start), *_segment(start, aside, 6), *_segment(aside, end, 5)]
    # same start, end and step count: the potential is path-independent, so only the
    # penalties tell the paths apart
    assert ret(proper, 0.0) == pytest.approx(ret(proper, W6))  # never unsafe
    flat_gap = ret(proper, 0.0) - ret(dive, 0.0)
    dist_gap = ret(proper, W6) - ret(dive, W6)
    assert 0 < flat_gap < 3.0  # the flat penalty: a few 0.3s, which a discount can outweigh
    # ... against more than the whole insertion from p_l to the end earns (flat 2.4, 19.25)
    assert dist_gap > W6 * (L - 0.02) and dist_gap > 5 * flat_gap, (flat_gap, dist_gap)
    # grazing: 0.5 mm outside the wall near the entrance costs 0.3 + 0.15, not a cliff
    flat, c, _ = _reward([0.0, 0, -0.048], 0.0, [0.006, 0, -0.048], 0.0)
    scaled, *_ = _reward([0.0, 0, -0.048], 0.0, [0.006, 0, -0.048], 0.0, k=W6)
    assert c.item() == 1.0 and (flat - scaled).item() == pytest.approx(W6 * 0.0005)
    # the cap bounds what one step can cost: 40 mm below p_l's plane and 30 mm aside
    far = ([0.03, 0, -0.02], 0.0, [0.03, 0, -0.01], 0.0)
    r_flat, *_ = _reward(*far)
    r_capped, *_ = _reward(*far, k=100.0, cap=0.01)
    assert (r_flat - r_capped).item() == pytest.approx(100.0 * 0.01)


def _paper_reward_unguarded(path, thetas):
    """The paper's piecewise formula as printed (no guard), for comparison."""
    pl = np.array([0.0, 0.0, -L])
    total = 0.0
    for a, b, ta, tb in zip(path[:-1], path[1:], thetas[:-1], thetas[1:], strict=True):
        reg = surgery_regions(torch.tensor(a[None]), torch.tensor([0.0055]), L).item()
        if reg == FREE:
            total += W4 * (np.linalg.norm(a - pl) - np.linalg.norm(b - pl)) + W5 * (ta - tb)
        elif reg == DRILL:
            total += W6 * (np.linalg.norm(a) - np.linalg.norm(b)) + W5 * (ta - tb)
    return total


def _segment(a, b, n):
    return [np.array(a) + (np.array(b) - np.array(a)) * k / n for k in range(1, n + 1)]


def test_no_closed_loop_through_the_unsafe_region_earns_reward():
    start = [0.0, 0.0, -0.07]
    # first descent: p_l, then down the corridor to 20 mm before the target
    path = [np.array(start)]
    path += _segment(start, [0, 0, -L], 4) + _segment([0, 0, -L], [0, 0, -0.02], 6)
    first = len(path)
    # the loop: out sideways (unsafe), up and far away through the unsafe region, back into
    # C_free 100 mm aside, over to the axis, down to p_l and the corridor to -20 mm again
    loop = _segment([0, 0, -0.02], [0.02, 0, -0.02], 2)
    loop += _segment([0.02, 0, -0.02], [0.10, 0.0, -0.045], 4)
    loop += _segment([0.10, 0.0, -0.045], [0.10, 0.0, -0.07], 2)
    loop += _segment([0.10, 0.0, -0.07], start, 6)
    loop += _segment(start, [0, 0, -L], 4) + _segment([0, 0, -L], [0, 0, -0.02], 6)
    path += loop * 3  # three times round
    thetas = [0.0] * len(path)
    p = torch.tensor(np.array(path), dtype=torch.float64)
    th = torch.tensor(thetas, dtype=torch.float64)
    hw = torch.tensor([0.0055], dtype=torch.float64)
    rewards, costs = [], []
    for k in range(1, len(path)):
        r, c, _ = surgery_reward(
            p[k - 1 : k], th[k - 1 : k], p[k : k + 1], th[k : k + 1], hw, L, W4, W5, W6, P
        )
        rewards.append(r.item())
        costs.append(c.item())
    rewards = np.array(rewards)
    descent = rewards[: first - 1].sum()
    assert descent == pytest.approx(W4 * 0.02 + W6 * 0.03)  # to p_l, then 30 mm deeper
    n = len(loop)
    for i in range(3):
        loop_costs = sum(costs[first - 1 + i * n : first - 1 + (i + 1) * n])
        ret = rewards[first - 1 + i * n : first - 1 + (i + 1) * n].sum()
        assert loop_costs > 0  # the loop did pass through the unsafe region
        # a closed path's potential terms cancel: only the unsafe steps' penalty remains
        assert ret == pytest.approx(-P * loop_costs, abs=1e-9), f"loop {i} earned {ret}"
    # the printed formula without the guard would have paid for every loop
    one_loop = np.array(path[first - 1 : first + n])
    unguarded_loop = _paper_reward_unguarded(one_loop, [0.0] * len(one_loop))
    assert unguarded_loop > 1.0


# ----------------------------------------------------------------------------- the env


def _spin(angle: float) -> torch.Tensor:
    return matrix_from_axis_angle(torch.tensor([[0.0, 0.0, angle]], dtype=torch.float64))[0]


def test_state_observation_is_position_and_drill_axes_continuous_at_180_degrees():
    # drill axis along z_G, 50 mm before the target, 1 mm / 2 mm off axis, no spin
    s = torch.tensor([[0.001, 0.002, -0.05, 0.0, 0.0, 0.0]], dtype=torch.float64)
    expected = torch.tensor([[0.001, 0.002, -0.05, 1, 0, 0, 0, 0, 1]], dtype=torch.float64)
    assert torch.allclose(state_observation(s), expected)
    # continuous where the rotation vector jumps: spins of pi -+ 1e-4 (with a tilt) have
    # rotation vectors ~2 pi apart, and observations 2e-4 rad of turn apart
    tilt = matrix_from_axis_angle(torch.tensor([[0.05, -0.03, 0.0]], dtype=torch.float64))[0]
    p = torch.tensor([0.003, -0.002, -0.03], dtype=torch.float64)
    near = [tilt @ _spin(math.pi + d) for d in (-1e-4, 1e-4)]
    rv = [axis_angle_from_matrix(r[None])[0] for r in near]
    assert float((rv[0] - rv[1]).norm()) > 6.0
    o = [state_observation(torch.cat([p, v])[None])[0] for v in rv]
    assert float((o[0] - o[1]).norm()) < 2e-4 * 1.01
    # in the env, every step: the position of info["state"], two orthonormal axes, and
    # z_D . z_G = cos theta
    env = _env(4, obs_mode="state")
    assert env.single_observation_space.shape == (9,)
    obs_t, info = env.reset(seed=3)
    g = torch.Generator().manual_seed(0)
    for _ in range(5):
        o, st = obs_t.double(), info["state"].double()
        assert torch.allclose(o[:, :3], st[:, :3])
        x_d, z_d = o[:, 3:6], o[:, 6:]
        for v in (x_d.norm(dim=-1), z_d.norm(dim=-1)):
            assert torch.allclose(v, torch.ones(4, dtype=torch.float64), atol=1e-6)
        assert torch.allclose((x_d * z_d).sum(-1), torch.zeros(4, dtype=torch.float64), atol=1e-6)
        theta = env.errors()["rotation_error_deg"].double() * math.pi / 180
        assert torch.allclose(z_d[:, 2], theta.cos(), atol=1e-5)
        obs_t, _, _, _, info = env.step(torch.randn(4, 6, generator=g))


def test_make_vec_gives_the_native_batched_env():
    env = _env(3, obs_mode="state")
    assert isinstance(env, SurgeryEnv)
    assert env.num_envs == 3 and env.episode_length == 600
    assert env.metadata["autoreset_mode"] == gym.vector.AutoresetMode.SAME_STEP
    assert env.single_action_space.shape == (6,)
    assert np.allclose(env.single_action_space.high, [0.3, 0.3, 0.3, 0.1, 0.1, 0.1])


def test_single_env_passes_gymnasium_checker():
    env = gym.make("SonoGym/Surgery-v0", **FAST)
    check_env(env.unwrapped, skip_render_check=True)


def test_observation_matches_its_declared_space():
    env = _env(2)
    obs, info = env.reset(seed=0)
    img, pose = obs["image"], obs["pose"]
    assert img.shape == (2, 5, 50, 37) and img.dtype == torch.float32
    assert pose.shape == (2, 7) and pose.dtype == torch.float32
    assert env.observation_space.contains({k: v.numpy() for k, v in obs.items()})
    # pose = drill tip in the probe frame {U}
    sc = env.scene
    rel = sc.probe_rot.transpose(-1, -2) @ (sc.tip_pos - sc.probe_pos).unsqueeze(-1)
    assert torch.allclose(pose[:, :3], rel.squeeze(-1), atol=1e-6)
    r_ud = sc.probe_rot.transpose(-1, -2) @ sc.tip_rot
    assert torch.allclose(matrix_from_quat(pose[:, 3:]), r_ud, atol=1e-5)
    obs, *_ = env.step(torch.zeros(2, 6))
    assert env.observation_space.contains({k: v.numpy() for k, v in obs.items()})
    lab_env = _env(1, obs_mode="labels")
    lab, _ = lab_env.reset(seed=0)
    assert lab["image"].dtype == torch.uint8
    assert lab_env.observation_space.contains({k: v.numpy() for k, v in lab.items()})


@pytest.mark.parametrize("simulator", ["physical", "reference"])
def test_volume_shows_the_vertebra_at_every_reset(simulator):
    env = _env(8, simulator=simulator)
    bright = 0.5 if simulator == "physical" else 0.15
    vertebrae = torch.tensor(list(VERTEBRA_IDS.values()), dtype=torch.uint8)
    for seed in (0, 1):  # 16 seeded resets
        obs, _ = env.reset(seed=seed)
        labels = env.scene.observe("labels")
        us = obs["image"]
        bone = torch.isin(labels, vertebrae)
        assert (bone.flatten(1).float().mean(1) > 0.05).all()  # the vertebra is in view
        assert (bone.flatten(1).any(1)).all()
        # a bright bone surface: the top bone voxel of bone columns
        below = torch.cumsum(bone.int(), dim=2) == 1
        surface = bone & below
        peak = torch.where(surface, us, torch.zeros_like(us)).flatten(1).amax(1)
        assert (peak > bright).all(), peak


def test_probe_placement_within_its_randomisation_range():
    env = _env(32, obs_mode="labels")
    env.reset(seed=3)
    sc = env.scene
    x, z, yaw, tilt = sc.measured_probe_command()
    centre = sc.target_centres
    dx = x - (centre[:, 0] - 0.03)  # right pedicle: probe on the patient's left
    dz = z - centre[:, 2]
    tol = 2e-4
    assert (dx.abs() <= 0.005 + tol).all() and (dz.abs() <= 0.005 + tol).all()
    assert dx.abs().max() > 0.003 and dz.abs().max() > 0.003  # the range is used
    assert torch.allclose(yaw, torch.full_like(yaw, math.pi / 2), atol=2e-3)
    assert torch.allclose(tilt, torch.full_like(tilt, -0.4), atol=2e-3)
    # the beam points toward the midline (+x from the left side)
    assert (sc.probe_rot[:, 0, 2] > 0.3).all()
    assert (sc.probe_reach_error < 1e-4).all()
    # the probe stays still during the episode
    pos = sc.probe_pos.clone()
    env.step(torch.ones(32, 6) * 0.1)
    assert torch.equal(sc.probe_pos, pos)


def test_state_mode_skips_the_probe_settle_and_keeps_the_same_drill_episodes():
    """The probe is not imaged in state mode, so it is not settled (it stays at its nominal
    pose); its offset is still drawn, so drill starts and steps match an imaging mode's."""
    state, labels = _env(6, obs_mode="state"), _env(6, obs_mode="labels")
    nominal = state.scene.probe_pos.clone()
    _, info_s = state.reset(seed=5)
    _, info_l = labels.reset(seed=5)
    assert torch.equal(state.scene.probe_pos, nominal)  # not settled
    assert not torch.allclose(labels.scene.probe_pos, nominal, atol=1e-4)  # settled, offset
    assert torch.equal(info_s["state"], info_l["state"])
    act = torch.rand(6, 6, generator=torch.Generator().manual_seed(0)) * 0.4 - 0.2
    for _ in range(3):
        _, r_s, _, _, info_s = state.step(act)
        _, r_l, _, _, info_l = labels.step(act)
    assert torch.equal(info_s["state"], info_l["state"]) and torch.equal(r_s, r_l)


def test_drill_starts_in_the_free_region():
    env = _env(64, obs_mode="state")
    _, info = env.reset(seed=5)
    assert (info["region"] == FREE).all()
    assert (info["cost"] == 0).all()
    nominal = _env(2, obs_mode="state", joint_noise=(0.0,) * 7)
    _, info = nominal.reset(seed=0)
    p = info["state"][:, :3]
    assert torch.allclose(p, torch.tensor([0.0, 0.0, -(L + 0.09)]).expand(2, 3), atol=1e-4)
    assert (nominal._theta < 1e-3).all()


def test_reward_and_cost_on_recorded_transitions():
    n = 8
    env = _env(n, obs_mode="state", episode_length=200)
    _, info = env.reset(seed=2)
    g = torch.Generator().manual_seed(0)
    half_width = (info["radius"] + 0.002).double().numpy()
    pl = np.array([0.0, 0.0, -L])
    states = [info["state"].double().numpy()]
    thetas = [env._theta.double().numpy()]
    rewards, costs = [], []
    for _ in range(150):
        a = surgery_expert(info["state"], info["radius"], position_gain=0.2)
        a = a + (torch.rand(n, 6, generator=g) - 0.5) * torch.tensor([0.1] * 3 + [0.02] * 3)
        _, r, _, _, info = env.step(a)
        states.append(info["state"].double().numpy())
        thetas.append(env._theta.double().numpy())
        rewards.append(r.double().numpy())
        costs.append(info["cost"].double().numpy())

    # an independent NumPy reading of the documented formula
    def region(p):
        lat = np.linalg.norm(p[:, :2], axis=1)
        free = p[:, 2] <= -L
        drill = ~free & (lat <= half_width) & (p[:, 2] <= 0)
        return np.where(free, FREE, np.where(drill, DRILL, UNSAFE))

    def phi(p, th):
        reg = region(p)
        out = -W4 * np.linalg.norm(p - pl, axis=1)
        d = W6 * (L - np.linalg.norm(p, axis=1))
        return np.where(reg == DRILL, d, out) - W5 * th

    checked_paper = 0
    for t in range(150):
        p0, p1, th0, th1 = states[t][:, :3], states[t + 1][:, :3], thetas[t], thetas[t + 1]
        unsafe = region(p1) == UNSAFE
        want = phi(p1, th1) - phi(p0, th0) - P * unsafe
        assert np.allclose(rewards[t], want, atol=2e-4), t
        assert np.array_equal(costs[t], unsafe.astype(float))
        # where both states are in C_free the paper's formula holds as printed
        both_free = (region(p0) == FREE) & (region(p1) == FREE)
        paper = W4 * (np.linalg.norm(p0 - pl, axis=1) - np.linalg.norm(p1 - pl, axis=1)) + W5 * (
            th0 - th1
        )
        assert np.allclose(rewards[t][both_free], paper[both_free], atol=2e-4)
        checked_paper += int(both_free.sum())
    assert checked_paper > 50
    assert np.concatenate(costs).sum() >= 0


def test_workspace_ball_stops_the_drill_wandering_off():
    c = torch.zeros(3, 3)
    pts = torch.tensor([[0.1, 0.0, 0.0], [0.0, 0.0, -0.5], [0.3, 0.4, 0.0]])
    out = clamp_to_ball(pts, c, torch.tensor([0.2, 0.2, 0.6]))
    torch.testing.assert_close(out, torch.tensor([[0.1, 0, 0], [0, 0, -0.2], [0.3, 0.4, 0]]))
    # pulling the drill straight back along its axis, as far as the arm allows, for 80 steps
    back = torch.zeros(4, 6)
    back[:, 2] = -0.3
    dist = {}
    for radius in (0.2, 10.0):
        env = _env(4, obs_mode="state", workspace_radius=radius)
        _, info = env.reset(seed=0)
        start = info["state"][:, :3].norm(dim=-1)
        for _ in range(80):
            _, _, _, _, info = env.step(back)
        dist[radius] = info["state"][:, :3].norm(dim=-1)
    # within the ball (or the start's distance, for starts beyond it), up to the IK's lag
    assert bool((dist[0.2] <= torch.maximum(start, torch.tensor(0.2)) + 2e-3).all())
    assert bool((dist[10.0] > 0.3).all())  # unbounded, the same pull goes much further


def test_over_fast_drill_command_leaves_a_tracking_error():
    env = _env(2, obs_mode="state", joint_noise=(0.0,) * 7)  # both envs at the nominal start
    env.reset(seed=0)
    before = env.scene.tip_pos.clone()
    a = torch.zeros(2, 6)
    a[0, 0] = 0.3  # 30 mm along x_D in one step: faster than the joints allow
    a[1, 0] = 10.0  # scaled by 0.1 m and clipped to the same 30 mm
    _, _, _, _, info = env.step(a)
    moved = (env.scene.tip_pos - before).norm(dim=-1)
    assert (info["tracking_error"] > 0.005).all() and (moved < 0.025).all()
    assert torch.allclose(env.scene.tip_pos[0], env.scene.tip_pos[1], atol=1e-6)
    # a slow command is tracked
    a = torch.zeros(2, 6)
    a[:, 2] = 0.01  # 1 mm along the drill axis
    _, _, _, _, info = env.step(a)
    assert (info["tracking_error"] < 1e-4).all()


def test_expert_reaches_the_target_safely():
    n = 64
    env = _env(n, obs_mode="state")
    _, info = env.reset(seed=123)
    final, _ = _run_expert(env, info, env.episode_length)
    ins, side = final["insertion_error_mm"], final["side_error_mm"]
    rot, safe = final["rotation_error_deg"], final["safe_ratio"]
    ok = (ins < 2.0) & (side < 1.0) & (rot < 2.0) & (safe == 1.0)
    assert ok.float().mean() >= 0.95, (ins.max(), side.max(), rot.max(), safe.min())
    assert (final["return"] > 10).all()


def test_left_pedicle_option():
    # labels mode: state mode does not settle the probe, and the placement is what is checked
    env = _env(4, obs_mode="labels", side="left", episode_length=250)
    _, info = env.reset(seed=0)
    sc = env.scene
    traj = sc.patients[0].landmarks.trajectory("L4", "left")
    assert np.allclose(sc.goal_pos[0].numpy(), traj.target, atol=1e-6)
    assert (sc.probe_pos[:, 0] > sc.target_centres[:, 0] + 0.02).all()  # probe on the right
    assert (sc.probe_rot[:, 0, 2] < -0.3).all()  # beam toward the midline
    final, _ = _run_expert(env, info, 250)
    assert (final["insertion_error_mm"] < 2).all() and (final["safe_ratio"] == 1).all()


def test_same_seed_same_episode_bit_for_bit():
    def run():
        env = _env(2)
        obs, _ = env.reset(seed=7)
        out = [obs["image"], obs["pose"]]
        g = torch.Generator().manual_seed(3)
        for _ in range(3):
            obs, r, *_ = env.step(torch.rand(2, 6, generator=g) * 0.2 - 0.1)
            out += [obs["pose"], r]
        return out

    a, b = run(), run()
    assert all(torch.equal(x, y) for x, y in zip(a, b, strict=True))


def test_autoreset_and_partial_reset():
    env = _env(2, episode_length=3)
    obs, info = env.reset(seed=0)
    for _ in range(3):
        obs, _, term, trunc, info = env.step(torch.zeros(2, 6))
    assert trunc.all() and not term.any()
    for k in ("insertion_error_mm", "side_error_mm", "rotation_error_deg", "safe_ratio"):
        assert info["final_info"][k].shape == (2,)
    assert (info["final_info"]["safe_ratio"] == 1).all()
    assert (env.episode_length_buf == 0).all()
    obs, *_ = env.step(torch.ones(2, 6) * 0.05)
    mask = torch.tensor([True, False])
    obs2, info2 = env.reset(options={"reset_mask": mask})
    assert torch.equal(obs2["pose"][1], obs["pose"][1])
    assert torch.equal(obs2["image"][1], obs["image"][1])
    assert env.episode_length_buf.tolist() == [0, 1]


def test_staggered_first_episodes_end_at_random_steps_then_run_whole():
    n, length = 16, 12
    ends = {}
    for stagger in (True, False):
        env = _env(n, obs_mode="state", episode_length=length)
        with pytest.raises(RuntimeError, match="reset"):
            env.stagger_episodes()
        env.reset(seed=4)
        if stagger:
            env.stagger_episodes()
        first = torch.zeros(n, dtype=torch.long)
        second = torch.zeros(n, dtype=torch.long)
        for t in range(1, 2 * length + 1):
            _, _, _, trunc, info = env.step(torch.zeros(n, 6))
            seen = first > 0
            second[seen & trunc & (second == 0)] = t
            first[~seen & trunc] = t
            if "final_info" in info:  # metrics of every ended episode, over its own steps
                assert bool((info["final_info"]["safe_ratio"] <= 1.0).all())
        ends[stagger] = (first, second)
    first, second = ends[True]
    assert bool((first >= 1).all() and (first <= length).all())
    assert len(set(first.tolist())) > 4  # spread out, not in lockstep
    assert torch.equal(second - first, torch.full((n,), length))  # then whole episodes
    assert torch.equal(ends[False][0], torch.full((n,), length))  # unstaggered: all at once


def test_bad_options_raise():
    with pytest.raises(ValueError, match="side"):
        _env(1, side="middle")
    with pytest.raises(ValueError, match="obs_mode"):
        _env(1, obs_mode="rgb")
    with pytest.raises(ValueError, match="joint_noise"):
        _env(1, joint_noise=(0.1, 0.1))
    with pytest.raises(TypeError, match="valid options"):
        _env(1, sid="left")
    with pytest.raises(ValueError, match="workspace_radius must be > 0"):
        _env(1, workspace_radius=0.0)
    with pytest.raises(ValueError, match="unsafe_distance_penalty .per m. and unsafe_distance_cap"):
        _env(1, unsafe_distance_penalty=-1.0)
    env = _env(1, obs_mode="state")
    env.reset(seed=0)
    with pytest.raises(ValueError, match="shape"):
        env.step(torch.zeros(1, 3))


def test_no_reward_trap_outside_the_safe_set():
    """The expert beats standing still, which beats every way of leaving the safe set or
    giving the insertion back (docs/design.md; the paper's "0 otherwise" paid +1.2 for
    a constant push along the drill axis). Six policies, four envs each, in one batch."""
    k, names = 4, ["expert", "still", "push-down", "dither", "deep, back out", "deep, out sideways"]
    n = k * len(names)
    env = _env(n, obs_mode="state")
    _, info = env.reset(seed=3)
    g = torch.Generator().manual_seed(0)
    group = torch.arange(n) // k
    deep = torch.zeros(n, dtype=torch.bool)  # reached 20 mm before the target
    back_out = torch.tensor([0.0, 0.0, -0.05, 0.0, 0.0, 0.0])
    sideways = torch.tensor([0.1, 0.0, 0.0, 0.0, 0.0, 0.0])
    for _ in range(env.episode_length):
        expert = surgery_expert(info["state"], info["radius"])
        deep |= info["state"][:, 2] > -0.02
        acts = [
            expert,
            torch.zeros(n, 6),
            torch.tensor([0.0, 0.0, 0.3, 0.0, 0.0, 0.0]).expand(n, 6),  # along the drill axis
            torch.randn(n, 6, generator=g),  # what an untrained sigma = 1 policy does
            torch.where(deep[:, None], back_out.expand(n, 6), expert),
            torch.where(deep[:, None], sideways.expand(n, 6), expert),
        ]
        a = torch.stack(acts)[group, torch.arange(n)]
        _, _, _, _, info = env.step(a)
    returns = info["final_info"]["return"].view(len(names), k)
    ret = dict(zip(names, returns, strict=True))
    assert (ret["still"] == 0).all()
    assert (ret["push-down"] < 0).all()  # leaves and stays out: less than standing still
    assert (ret["deep, out sideways"] < 0).all()
    assert ret["dither"].mean() < 0
    assert (ret["deep, back out"] < ret["expert"]).all()  # backing out gives the depth back
    assert ret["expert"].min() > returns[1:].max()  # the expert's return is the largest


def test_corridor_damping_slows_lateral_and_rotational_motion_inside_c_drill():
    d = torch.tensor([[0.01, -0.02, 0.03, 0.1, -0.1, 0.05]] * 2)
    inside = torch.tensor([True, False])
    out = corridor_damping(d, inside, 0.2)
    assert torch.allclose(out[0], d[0] * torch.tensor([0.2, 0.2, 1.0, 0.2, 0.2, 0.2]))
    assert torch.equal(out[1], d[1])  # outside C_drill nothing changes
    # in the env: a tip on the axis in the corridor moves a fifth as far sideways (1: off)
    moved = {}
    for damping in (0.2, 1.0):
        env = _env(1, obs_mode="state", corridor_damping=damping)
        _, info = env.reset(seed=0)
        for _ in range(400):  # the expert takes the tip into the corridor
            _, _, _, _, info = env.step(surgery_expert(info["state"], info["radius"]))
        assert info["region"].item() == DRILL
        before = info["state"][0, :2].clone()
        _, _, _, _, info = env.step(torch.tensor([[0.02, 0.0, 0.0, 0.0, 0.0, 0.0]]))
        moved[damping] = float((info["state"][0, :2] - before).norm())
    assert moved[0.2] == pytest.approx(0.2 * moved[1.0], rel=0.05)
    assert moved[1.0] == pytest.approx(0.002, rel=0.05)  # 0.02 units x 0.1 m


def test_cpu_preset_action_box_is_one_the_drill_arm_realises():
    """The cpu preset's per-step action box: each component at its limit is realised in one
    control step, and at any corner the axial command keeps most of its motion. Under the
    reference's box (30 mm, 0.1 rad: 18-62 % of a lone component realised, 8 % of the axial
    push at the worst corner) the joint speed limits scale a command down whole, so saturated
    lateral or rotation commands froze the drill above p_l and a trained seed hovered there."""
    import itertools

    from sonogym.agents.configs import resolve_train_config

    preset = resolve_train_config("surgery", "ppo", preset="cpu").rl.env_kwargs
    n = 32
    env = _env(n, obs_mode="state", **preset)
    _, info = env.reset(seed=0)
    for _ in range(100):  # the expert's approach, held 10 mm above p_l (in C_free)
        a = surgery_expert(info["state"], info["radius"])
        a = torch.where((info["state"][:, 2] > -L - 0.01)[:, None], torch.zeros_like(a), a)
        _, _, _, _, info = env.step(a)
    assert bool((info["region"] == FREE).all())
    start = (env.scene.q_drill.clone(), env.scene.tip_pos.clone(), env.scene.tip_rot.clone())
    state, region = env._state.clone(), env._region.clone()
    high = torch.as_tensor(env.single_action_space.high)

    def step_from_start(action):
        env.scene.q_drill, env.scene.tip_pos, env.scene.tip_rot = (t.clone() for t in start)
        env._state, env._region = state.clone(), region.clone()
        env.scene.drill_arm._last_frames = None
        _, _, _, _, out = env.step(action)
        return out

    limit = env.cfg.action_limit
    for i in range(6):  # one component at its limit, the others 0: realised in full
        a = torch.zeros(n, 6)
        a[:, i] = high[i]
        step_from_start(a)
        if i < 3:
            moved = (env.scene.tip_pos - start[1]).norm(dim=-1)
        else:
            rel = start[2].transpose(-1, -2) @ env.scene.tip_rot
            moved = axis_angle_from_matrix(rel).norm(dim=-1)
        assert float(moved.min()) > 0.99 * limit[i], (i, float(moved.min()))
    # every sign pattern of the other five at their limits, full axial push
    signs = torch.tensor(list(itertools.product([-1.0, 1.0], repeat=5)))
    a = high.repeat(n, 1)
    a[:, [0, 1, 3, 4, 5]] *= signs
    axial = step_from_start(a)["state"][:, 2] - state[:, 2]
    assert float(axial.mean()) > 0.7 * limit[2] and float(axial.min()) > 0.4 * limit[2]
