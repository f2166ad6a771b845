"""Training speed against the env's own: how much of a PPO run's wall time the learner takes.

    python benchmarks/learner.py [--recipes navigation surgery-state] [--envs 64] [--threads 1]
                                 [--updates 3] [--rounds 3] [--json out.json]
                                 [--baseline old.json]

Per recipe (the ``cpu`` preset's; ``surgery-state`` is Table 1's surgery recipe: privileged
state observations, ``--net lean``), alternating ``--rounds`` times in one process:

* **env alone**: env-steps/s of the env stepping with random actions through the trainer's
  adapter (``SkrlEnvAdapter.step``: simulation and observations), what the training loop
  counts as the env's time;
* **training**: a ``run_training`` of ``--updates`` PPO updates at the same envs and threads
  (``TrainResult.speed``): its env-steps/s, the learner's share of its loop's wall time
  (everything but the env's steps) and the updates' share.

"training / env" is the training's env-steps/s over the env's own (the budget: >= 0.7), by
wall time and by CPU time (the process's; steadier than wall time on a machine other jobs
share: a single-threaded run's wall time there is 1.5-2x its CPU time, unevenly). Medians
over the rounds. Then the parts of one update, timed on a rollout the run's own
policy collected (CPU seconds, median of 3): the mini-batch passes forward (policy and value
share one encoder pass), backward, gradient clipping and the Adam step, cumulatively
measured. Prints one table; ``--baseline`` adds the training env-steps/s ratio to a saved
JSON.
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path

import torch
import torch.nn.functional as F

RECIPES = {
    "navigation": dict(task="navigation"),
    "surgery-state": dict(
        task="surgery", net="lean",
        env_kwargs={"obs_mode": "state", "unsafe_distance_penalty": 100.0},
    ),
}  # fmt: skip


def config(recipe: str, envs: int, threads: int, steps: int):
    from sonogym.agents.configs import resolve_train_config

    kw = dict(RECIPES[recipe])
    task = kw.pop("task")
    return resolve_train_config(
        task, "ppo", preset="cpu", envs=envs, threads=threads, steps=steps, seed=0, **kw
    )


def env_alone(cfg, steps: int) -> tuple[float, float]:
    """(env-steps per wall second, per CPU second) of the run's env and adapter stepping with
    uniform random actions."""
    from sonogym.agents.adapter import SkrlEnvAdapter
    from sonogym.agents.train import make_env

    torch.set_num_threads(cfg.threads)
    env = make_env(cfg.rl, cfg.rl.num_envs, cfg.device)
    try:
        learning = cfg.rl.learning
        adapter = SkrlEnvAdapter(
            env, cfg.rl.obs_downsample, learning.obs_scales, seed=cfg.seed,
            standardize_vectors=learning.standardize_vectors,
            stagger_episodes=learning.stagger_episodes,
        )  # fmt: skip
        adapter.update_stats = True
        adapter.reset()
        space = adapter.action_space
        low, high = torch.as_tensor(space.low), torch.as_tensor(space.high)
        g = torch.Generator().manual_seed(0)
        n = cfg.rl.num_envs

        def act() -> torch.Tensor:
            return low + (high - low) * torch.rand(n, low.shape[0], generator=g)

        for _ in range(2):
            adapter.step(act())
        actions = [act() for _ in range(steps)]
        t0, c0 = time.perf_counter(), time.process_time()
        for a in actions:
            adapter.step(a)
        return n * steps / (time.perf_counter() - t0), n * steps / (time.process_time() - c0)
    finally:
        env.close()


def training(cfg) -> dict[str, float]:
    """The run's ``TrainResult.speed`` and "per_cpu_s": env-steps per CPU second of its loop
    (``times.json``)."""
    from sonogym.agents.train import read_times, run_training

    with tempfile.TemporaryDirectory() as d:
        res = run_training(cfg, Path(d) / "run", progress=False, log=lambda m: None)
        cpu_s = read_times(res.out / "checkpoints")[res.steps]["cpu_s"]
    return {**res.speed, "per_cpu_s": res.steps * cfg.rl.num_envs / cpu_s}


def update_parts(cfg, repeats: int = 3) -> dict[str, float]:
    """CPU seconds of one update's mini-batch passes (all epochs), cumulatively: "forward",
    "backward" (forward + backward), "clip" (+ gradient clipping), "adam" (+ optimiser step),
    on the rollout memory after one real rollout and update of the run's policy."""
    from sonogym.agents.train import TrainingSpeed, _EpisodeMeans, _set_up, _step, make_env

    torch.manual_seed(cfg.seed)
    env = make_env(cfg.rl, cfg.rl.num_envs, cfg.device)
    try:
        with tempfile.TemporaryDirectory() as d:
            run = _set_up(cfg, Path(d) / "run", env, 0)
            agent, adapter = run.agent, run.adapter
            agent.enable_training_mode(True)
            obs, _ = adapter.reset()
            r = cfg.params.rollouts
            speed = TrainingSpeed(cfg.rl.num_envs)
            for t in range(r):  # a rollout and its update: the memory holds its advantages
                obs = _step(agent, adapter, obs, t, r, _EpisodeMeans(), speed)
            agent.enable_models_training_mode(True)
            return _time_parts(agent, cfg.params.learning_epochs, repeats)
    finally:
        env.close()


def _time_parts(agent, epochs: int, repeats: int) -> dict[str, float]:
    model, opt, mem = agent.policy, agent.optimizer, agent.memory
    params = list(model.parameters())
    names = agent._tensors_names
    batches = mem.sample(names=names, batch_size=len(mem), mini_batches=agent.cfg.mini_batches)
    stages = ("forward", "backward", "clip", "adam")

    def passes(stage: str) -> None:
        for _ in range(epochs):
            for obs, states, actions, log_prob, _, returns, advantages in batches:
                inputs = {"observations": obs, "states": states}
                _, out = model.act({**inputs, "taken_actions": actions}, role="policy")
                value, _ = model.act(inputs, role="value")
                ratio = torch.exp(out["log_prob"] - log_prob)
                loss = -(advantages * ratio).mean() + F.mse_loss(returns, value)
                if stage == "forward":
                    continue
                opt.zero_grad()
                loss.backward()
                if stage == "backward":
                    continue
                torch.nn.utils.clip_grad_norm_(params, 1.0)
                if stage == "clip":
                    continue
                opt.step()

    times = {s: [] for s in stages}
    for _ in range(repeats):
        for s in stages:
            t0 = time.process_time()
            passes(s)
            times[s].append(time.process_time() - t0)
    return {s: statistics.median(v) for s, v in times.items()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--recipes", nargs="+", default=list(RECIPES), choices=list(RECIPES))
    ap.add_argument("--envs", type=int, default=64)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--updates", type=int, default=3, help="PPO updates per training run")
    ap.add_argument("--rounds", type=int, default=3, help="env-alone / training alternations")
    ap.add_argument("--json", type=Path, default=None, help="save the rows here")
    ap.add_argument("--baseline", type=Path, default=None, help="a saved --json to compare with")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    load0 = Path("/proc/loadavg").read_text().split()[0]
    rows = []
    for recipe in args.recipes:
        probe = config(recipe, args.envs, args.threads, 1)
        cfg = config(recipe, args.envs, args.threads, args.updates * probe.params.rollouts)
        alone, runs = [], []
        for _ in range(args.rounds):
            alone.append(env_alone(cfg, cfg.params.rollouts))
            runs.append(training(cfg))
        med = {k: statistics.median(r[k] for r in runs) for k in runs[0]}
        parts = update_parts(cfg)
        rows.append({
            "recipe": recipe, "envs": args.envs, "threads": args.threads,
            "env_alone": statistics.median(a[0] for a in alone), "training": med["env_steps_per_s"],
            "env_alone_cpu": statistics.median(a[1] for a in alone),
            "training_cpu": med["per_cpu_s"],
            "learner_share": med["learner_share"], "update_share": med["update_share"],
            "update_s": med["update_s"] / args.updates, **{f"{k}_s": v for k, v in parts.items()},
        })  # fmt: skip
    load1 = Path("/proc/loadavg").read_text().split()[0]
    base = {}
    if args.baseline:
        base = {r["recipe"]: r for r in json.loads(args.baseline.read_text())}
    print(f"PPO, cpu preset, {args.updates} updates per run, median of {args.rounds} "
          f"alternations; load average {load0} -> {load1}")  # fmt: skip
    print(
        "| recipe | envs | threads | env alone env-steps/s | training env-steps/s | "
        "training / env | same, per CPU s | learner | updates | update s (wall) | forward / "
        "+ backward / + clip / + Adam (CPU s) | vs baseline |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        b = base.get(r["recipe"])
        ratio = f"{r['training'] / b['training']:.2f}x" if b else "-"
        parts = " / ".join(f"{r[f'{k}_s']:.2f}" for k in ("forward", "backward", "clip", "adam"))
        print(
            f"| {r['recipe']} | {r['envs']} | {r['threads']} | {r['env_alone']:.0f} | "
            f"{r['training']:.0f} | {r['training'] / r['env_alone']:.2f} | "
            f"{r['training_cpu']:.0f} / {r['env_alone_cpu']:.0f} = "
            f"{r['training_cpu'] / r['env_alone_cpu']:.2f} | "
            f"{100 * r['learner_share']:.0f}% | {100 * r['update_share']:.0f}% | "
            f"{r['update_s']:.2f} | {parts} | {ratio} |"
        )
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
