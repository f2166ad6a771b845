"""Returns of simple policies on the surgery task (state observations): the expert, standing
still, unit-noise actions, backing out of or leaving the corridor, pushing along the drill
axis. The table in benchmarks/README.md ("Surgery reward: returns of simple policies") comes
from

    python benchmarks/surgery_policy_returns.py [spacing_m=0.001] [seed=0] [w5_per_rad=5] [k=0]

(w5 = 50, k = 100: the tilt weight and the unsafe distance penalty the ``cpu`` training preset
trains surgery with.)
"""

import sys

import torch

from sonogym.envs.registry import make_vec
from sonogym.envs.surgery import surgery_expert

N = 32


def unit(i: int, value: float) -> torch.Tensor:
    a = torch.zeros(N, 6)
    a[:, i] = value
    return a


def then(trigger_z: float, action: torch.Tensor):
    """The expert until the tip passes p_z = trigger_z (m in {G}), then ``action`` forever."""

    def policy(info, g, mem):
        mem |= info["state"][:, 2] > trigger_z
        return torch.where(mem[:, None], action, surgery_expert(info["state"], info["radius"]))

    return policy


POLICIES = {
    "expert": lambda info, g, mem: surgery_expert(info["state"], info["radius"]),
    "standing still": lambda info, g, mem: torch.zeros(N, 6),
    "unit-noise actions": lambda info, g, mem: torch.randn(N, 6, generator=g),
    "expert, then stop at p_l": then(-0.052, torch.zeros(N, 6)),
    "expert, then back out": then(-0.005, unit(2, -0.05)),
    "expert, then out sideways": then(-0.02, unit(0, 0.1)),
    "push along the drill axis": lambda info, g, mem: unit(2, 0.3),
}


def main() -> None:
    torch.set_num_threads(1)
    spacing = float(sys.argv[1]) if len(sys.argv) > 1 else 0.001
    seed = int(sys.argv[2]) if len(sys.argv) > 2 else 0
    w5 = float(sys.argv[3]) if len(sys.argv) > 3 else 5.0
    k = float(sys.argv[4]) if len(sys.argv) > 4 else 0.0
    env = make_vec(
        "surgery", N, obs_mode="state", phantom_spacing=spacing, w5=w5, unsafe_distance_penalty=k
    )
    print("| policy | return | safe ratio | insertion mm | side mm |\n|---|---|---|---|---|")
    for name, policy in POLICIES.items():
        _, info = env.reset(seed=seed)
        g = torch.Generator().manual_seed(1)
        mem = torch.zeros(N, dtype=torch.bool)
        for _ in range(env.episode_length):
            _, _, _, _, info = env.step(policy(info, g, mem))
        f = info["final_info"]
        print(
            f"| {name} | {f['return'].mean():.2f} ± {f['return'].std():.2f} "
            f"| {f['safe_ratio'].mean():.3f} | {f['insertion_error_mm'].mean():.1f} "
            f"| {f['side_error_mm'].mean():.1f} |"
        )


if __name__ == "__main__":
    main()
