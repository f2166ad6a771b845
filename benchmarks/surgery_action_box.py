"""How much of a surgery command the drill arm realises in one control step, for the
reference's per-step action box and the ``cpu`` training preset's. The figures in
benchmarks/README.md ("Surgery action box: what the drill arm realises in one step") come from

    python benchmarks/surgery_action_box.py [spacing_m=0.001] [seed=0]

From the expert's approach held 10 mm above p_l (in C_free, no corridor damping), each row
steps 32 envs once from the same arm states: one component at the box's limit, the others 0
(the motion or rotation realised, as a fraction of the command, least over the envs), then the
full axial push with the other five components at every sign pattern of their limits (the
axial motion realised, as a fraction of the command: mean and least).
A command the joint speed limits cannot follow is scaled down whole (``Arm.ik_step``), so an
unrealisable lateral or rotation command slows the push along the drill axis too.
"""

import itertools
import sys

import torch

from sonogym.envs.registry import make_vec
from sonogym.envs.surgery import CPU_ACTION_LIMIT, SurgeryConfig, surgery_expert
from sonogym.geometry import axis_angle_from_matrix

N = 32
BOXES = {"reference": SurgeryConfig().action_limit, "cpu preset": CPU_ACTION_LIMIT}
NAMES = ("x", "y", "z", "wx", "wy", "wz")


def approach(env, seed: int) -> dict:
    """The expert's approach, held 10 mm above p_l."""
    _, info = env.reset(seed=seed)
    hold = -(env.cfg.skin_distance + 0.01)
    for _ in range(100):
        a = surgery_expert(info["state"], info["radius"])
        a = torch.where((info["state"][:, 2] > hold)[:, None], torch.zeros_like(a), a)
        _, _, _, _, info = env.step(a)
    return info


def realised(box: tuple[float, ...], spacing: float, seed: int) -> tuple[list[float], torch.Tensor]:
    """(least fraction realised of each component alone, (N,) axial fraction at the corners)."""
    env = make_vec("surgery", N, obs_mode="state", phantom_spacing=spacing, action_limit=box)
    approach(env, seed)
    sc = env.scene
    start = (sc.q_drill.clone(), sc.tip_pos.clone(), sc.tip_rot.clone())
    state, region = env._state.clone(), env._region.clone()
    high = torch.as_tensor(env.single_action_space.high)

    def step_from_start(action):
        sc.q_drill, sc.tip_pos, sc.tip_rot = (t.clone() for t in start)
        env._state, env._region = state.clone(), region.clone()
        sc.drill_arm._last_frames = None
        _, _, _, _, out = env.step(action)
        return out

    alone = []
    for i in range(6):
        a = torch.zeros(N, 6)
        a[:, i] = high[i]
        step_from_start(a)
        if i < 3:
            moved = (sc.tip_pos - start[1]).norm(dim=-1)
        else:
            moved = axis_angle_from_matrix(start[2].transpose(-1, -2) @ sc.tip_rot).norm(dim=-1)
        alone.append(float(moved.min()) / box[i])
    signs = torch.tensor(list(itertools.product([-1.0, 1.0], repeat=5)))
    a = high.repeat(N, 1)
    a[:, [0, 1, 3, 4, 5]] *= signs
    axial = step_from_start(a)["state"][:, 2] - state[:, 2]
    return alone, axial / box[2]


def main() -> None:
    torch.set_num_threads(1)
    spacing = float(sys.argv[1]) if len(sys.argv) > 1 else 0.001
    seed = int(sys.argv[2]) if len(sys.argv) > 2 else 0
    print(
        "| box | " + " | ".join(f"{n} alone" for n in NAMES)
        + " | axial at the corners: mean | min |\n" + "|---" * 9 + "|"
    )  # fmt: skip
    for name, box in BOXES.items():
        alone, corners = realised(box, spacing, seed)
        print(
            f"| {name} {box} | " + " | ".join(f"{f:.2f}" for f in alone)
            + f" | {float(corners.mean()):.2f} | {float(corners.min()):.2f} |"
        )  # fmt: skip


if __name__ == "__main__":
    main()
