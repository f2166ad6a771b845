"""How well a ppo-sf run's cost critic knows its own policy: Q_c along deterministic rollouts.

Runs the run's unfiltered policy for one episode in N envs (the run's env options), records
Q_c of the policy's action, of no motion and of the action halved, and the cost each step
caused; prints the AUC of Q_c against the cost and, for the first unsafe entries, the steps
around them. Nothing is written to the run.

    python scripts/safety_filter_probe.py runs/surg-img-sf-anneal-s0 --envs 20
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from sonogym.agents.checkpoint import load_cost_critic
from sonogym.envs.registry import make_vec
from sonogym.evaluation.rl_eval import controller_policy
from sonogym.evaluation.trained import load_run


def auc(score: np.ndarray, label: np.ndarray) -> float:
    """Probability that a positive outscores a negative (ties half), by ranks."""
    order = np.argsort(score, kind="stable")
    ranks = np.empty(len(score))
    ranks[order] = np.arange(1, len(score) + 1)
    pos = label > 0
    n_pos, n_neg = int(pos.sum()), int((~pos).sum())
    return float((ranks[pos].sum() - n_pos * (n_pos + 1) / 2) / (n_pos * n_neg))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run")
    ap.add_argument("--envs", type=int, default=20)
    ap.add_argument("--seed", type=int, default=1000)
    args = ap.parse_args()
    torch.set_num_threads(1)
    trained = load_run(args.run)
    env = make_vec(trained.task, args.envs, **trained.env_kwargs)
    policy = controller_policy("unfiltered", env, trained, args.seed)
    critic, threshold, _ = load_cost_critic(args.run)
    obs, info = env.reset(seed=args.seed)
    rows: dict[str, list] = {"q_action": [], "q_still": [], "q_half": [], "cost": []}
    with torch.no_grad():
        for _ in range(env.cfg.episode_length):
            x = policy.adapter.flatten(obs)
            a = policy.model.act({"observations": x}, role="policy")[1]["mean_actions"]
            q = critic.q_values(x, torch.stack([a, torch.zeros_like(a), 0.5 * a]))
            obs, _, _, _, info = env.step(a)
            for k, v in zip(("q_action", "q_still", "q_half"), q, strict=True):
                rows[k].append(v)
            rows["cost"].append(info["cost"].float())
    r = {k: torch.stack(v).numpy() for k, v in rows.items()}  # (T, N)
    cost = r["cost"]
    print(f"{args.envs} episodes, unsafe steps {cost.mean():.1%}, threshold {threshold}")
    print(f"AUC of Q_c(o, a) against the cost: {auc(r['q_action'].ravel(), cost.ravel()):.4f}")
    false_alarm = (r["q_action"][cost == 0] > threshold).mean()
    missed = (r["q_action"][cost == 1] <= threshold).mean()
    print(f"safe steps rated > threshold: {false_alarm:.2%}; unsafe rated <= it: {missed:.2%}")
    np.set_printoptions(precision=2, suppress=True, linewidth=160)
    for e in np.flatnonzero(cost.any(0))[:3]:
        t = int(np.argmax(cost[:, e] > 0))
        s = slice(max(t - 3, 0), t + 5)
        print(f"env {e}: first unsafe step {t}")
        for k in ("cost", "q_action", "q_still", "q_half"):
            print(f"  {k:9s}", r[k][s, e])


if __name__ == "__main__":
    main()
