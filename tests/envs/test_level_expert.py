import math

import gymnasium as gym
import pytest
import torch

import sonogym  # noqa: F401
from sonogym.envs.level_expert import LevelCountingExpert, caudal_waypoints
from sonogym.envs.navigation import SPEC
from sonogym.envs.rollout import rollout

FAST = dict(patients=(0, 1), phantom_spacing=0.002, obs_mode="state")
#: (dx, dz, yaw) of the starts: the start square's corners and edges (m, m, rad)
CORNERS = [
    (dx, dz, yaw) for dx in (-0.065, 0.065) for dz in (0.065, 0.0, -0.065) for yaw in (1.5, 3.5)
]


def _cornered_env(**kw):
    """Envs whose episodes start at ``CORNERS`` (env i: corner i // 2, patient i % 2)."""
    n = 2 * len(CORNERS)
    env = gym.make_vec("SonoGym/Navigation-v0", num_envs=n, **{**FAST, **kw})
    off = torch.tensor([c for c in CORNERS for _ in range(2)], dtype=torch.float32)

    def starts(env_ids, goal, half, yaw):
        g, o = goal[env_ids], off[env_ids]
        return torch.stack([g[:, 0] + o[:, 0], g[:, 1] + o[:, 1], o[:, 2]], -1)

    env.draw_surface_starts = starts
    return env


def test_the_waypoint_lies_one_level_below_l5_over_the_sacrum():
    env = gym.make_vec("SonoGym/Navigation-v0", num_envs=2, **FAST)
    z_w = caudal_waypoints(env.scene)
    for p, patient in enumerate(env.scene.patients):
        c4 = patient.landmarks.vertebra("L4").centre
        c5 = patient.landmarks.vertebra("L5").centre
        level = c4[2] - c5[2]
        assert 0.02 < level < 0.05
        # the aimed beam leans (the skin's normal): the point lies within ~half a level
        assert c5[2] - 1.6 * level < float(z_w[p]) < c5[2] - 0.4 * level
    assert (LevelCountingExpert(env).waypoint_z < env.goal_cmd[:, 1] - 0.05).all()


@pytest.mark.parametrize("robot", ["kuka_med14", None])
def test_it_visits_the_waypoint_then_reaches_the_goal_from_every_corner(robot):
    env = _cornered_env(robot=robot)
    expert = LevelCountingExpert(env)
    lowest = torch.full((env.num_envs,), math.inf)
    steps_to_goal = torch.full((env.num_envs,), -1)
    for step in rollout(env, expert, 120, seed=0):
        if step.t == 0:
            start_z = step.info["measured_command"][:, 1].clone()
        lowest = torch.minimum(lowest, step.next_info["measured_command"][:, 1])
        pos, ang = env.errors()
        at_goal = (pos < 1.0) & (ang < 1.0) & expert.reached & (steps_to_goal < 0)
        steps_to_goal[at_goal] = step.t + 1
    above = start_z > expert.waypoint_z
    assert bool(above.all())  # every corner starts above the waypoint
    assert (lowest <= expert.waypoint_z).all()
    # the worst corner (cranial, yaw 1.5 rad) needs ~85 of the episode's 300 steps with the arm
    assert (steps_to_goal > 0).all() and int(steps_to_goal.max()) <= 100
    pos, ang = env.errors()
    assert float(pos.max()) < 1.0 and float(ang.max()) < 1.0


def test_from_below_the_waypoint_it_is_the_papers_expert():
    env = gym.make_vec("SonoGym/Navigation-v0", num_envs=4, **FAST)
    expert = LevelCountingExpert(env)
    expert.waypoint_z = torch.full_like(expert.waypoint_z, 1.0)  # every start lies below
    _, info = env.reset(seed=3)
    expert.reset()
    for _ in range(5):
        a = expert.act(None, info)
        torch.testing.assert_close(a, SPEC.expert(env, info))
        _, _, _, _, info = env.step(a)


def test_partial_reset_forgets_the_waypoint_only_for_the_restarted_envs():
    env = gym.make_vec("SonoGym/Navigation-v0", num_envs=4, **FAST)
    expert = LevelCountingExpert(env)
    _, info = env.reset(seed=0)
    expert.reset()
    for _ in range(100):
        _, _, _, _, info = env.step(expert.act(None, info))
    assert expert.reached.all()
    at_goal_z = info["measured_command"][:, 1].clone()
    restarted = torch.tensor([True, False, True, False])
    expert.reset(restarted)
    assert expert.reached.tolist() == [False, True, False, True]
    for _ in range(5):
        _, _, _, _, info = env.step(expert.act(None, info))
    moved = (info["measured_command"][:, 1] - at_goal_z) * 1e3  # mm
    assert (moved[restarted] < -20).all()  # heading for the sacrum again
    assert (moved[~restarted].abs() < 0.5).all()  # staying at {G}


def test_every_episode_of_a_rollout_goes_down_to_the_waypoint():
    env = gym.make_vec("SonoGym/Navigation-v0", num_envs=6, **FAST, episode_length=60)
    expert = LevelCountingExpert(env)
    lowest = torch.full((env.num_envs,), math.inf)
    episodes = 0
    for step in rollout(env, expert, 180, seed=1):
        z = step.info["measured_command"][:, 1]  # the state each action starts from
        if step.t % 60 == 0:
            start_z = z.clone()
        lowest = torch.minimum(lowest, z)
        if step.ended:  # every env ends together: episode_length 60
            above = start_z > expert.waypoint_z
            assert (lowest[above] <= expert.waypoint_z[above]).all()
            lowest.fill_(math.inf)
            episodes += 1
    assert episodes == 3


def test_it_needs_a_navigation_env():
    env = gym.make_vec("SonoGym/Surgery-v0", num_envs=1, patients=(0,), phantom_spacing=0.002)
    with pytest.raises(TypeError, match="navigation env"):
        LevelCountingExpert(env)
    nav = gym.make_vec("SonoGym/Navigation-v0", num_envs=1, **FAST)
    with pytest.raises(ValueError, match="overshoot"):
        LevelCountingExpert(nav, overshoot=0.0)
    assert SPEC.expert_factory("level-counting") is LevelCountingExpert
    with pytest.raises(ValueError, match="level-counting"):
        SPEC.expert_factory("levels")
