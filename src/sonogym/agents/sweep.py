"""Seeds and hyperparameter sweeps on Ray Tune: ``sweep(task, algo, out, seeds=3, grid=...)``.

Every trial is one ``TrainConfig`` (the sweep's base config, resolved like ``sonogym train``'s,
with the trial's seed and grid values) run by ``run_training`` into the normal run layout under
``out/runs/<task>-<algo>[-key=value...]-s<seed>``, so ``sonogym eval``, ``plot`` and
``report`` work on it unchanged. Trials report their recent episode metrics to Tune at every
checkpoint (``tune.report`` with the checkpoint), run with the preset's CPU threads (and a
share of the GPU on CUDA), and a trial that raises is reported as errored while the others
finish. ``resume=True`` continues an interrupted sweep (``Tuner.restore``): finished trials are
not rerun, an interrupted trial resumes from its newest checkpoint.

At the end ``out/sweep.md`` / ``sweep.csv`` hold one row per trial (its seed and grid values,
status, final metrics); ``sonogym sweep`` then draws the mean ± 1 sigma learning curves over
seeds into ``out/plots`` (``sonogym plot --runs out/runs``).

Grid keys: ``num_envs``, ``net``, ``obs_downsample``, ``reward_scale``, ``init_log_std``,
``final_log_std``, ``anneal_steps``, ``mean_bound_penalty``, ``standardize_steps``,
``kl_follows_sigma`` (the task config),
``<algorithm>.<field>`` (the run's algorithm config, e.g. ``ppo.learning_rate``),
``env.<option>`` (an env option).
Ray runs locally unless ``address`` names a cluster (``ray://host:10001``).
"""

from __future__ import annotations

import csv
import io
import shutil
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sonogym.agents.configs import (
    TrainConfig,
    apply_settings,
    check_setting_key,
    resolve_train_config,
)
from sonogym.envs.options import parse_value
from sonogym.runs import (
    atomic_write_json,
    atomic_write_text,
    deleted_message,
    prepare_output,
    read_json,
)

RAY_HINT = "sonogym sweep needs Ray Tune: pip install 'sonogym[ray]' (or pip install 'ray[tune]')"
SWEEP_FILE = "sweep.json"


@dataclass(frozen=True)
class TrialRow:
    name: str
    params: dict[str, Any]  # seed and grid values
    status: str  # TERMINATED, ERROR, ...
    metrics: dict[str, float]  # the last report
    error: str | None


@dataclass(frozen=True)
class SweepResult:
    out: Path
    trials: tuple[TrialRow, ...]


def import_ray():
    try:
        import ray
        from ray import tune
    except ImportError:
        raise ImportError(RAY_HINT) from None
    return ray, tune


def parse_grid(items: list[str] | None) -> dict[str, list[Any]]:
    """``["ppo.learning_rate=1e-4,3e-4", "net=small,paper"]`` -> {key: [values]}."""
    grid: dict[str, list[Any]] = {}
    for item in items or []:
        key, sep, vals = item.partition("=")
        if not sep or not vals:
            raise ValueError(f"grid entry {item!r}: write key=value1,value2")
        check_key(key)
        grid[key] = [parse_value(v) for v in vals.split(",")]
    return grid


def check_key(key: str) -> None:
    check_setting_key(key, "grid key")


def apply(base: TrainConfig, params: dict[str, Any]) -> TrainConfig:
    """``base`` with a trial's seed and grid values (``apply_settings``)."""
    return apply_settings(base, params, "grid key")


def check_sweep_memory(configs: list[TrainConfig], trials: int, max_concurrent: int | None):
    """Refuse a sweep whose trials running at once (``max_concurrent``, else as many as the
    CPUs hold at each trial's threads) would not fit in memory with their envs, the largest
    grid point counted for each (each trial checks its own training memory when it starts)."""
    import os

    from sonogym.envs.footprint import config_memory
    from sonogym.envs.registry import env_config, get_task
    from sonogym.memory import check_fits, free_memory

    threads = max(c.threads or 1 for c in configs)
    at_once = min(trials, max_concurrent or max(1, (os.cpu_count() or 1) // threads))
    need = max(
        config_memory(get_task(c.task).memory, c.rl.num_envs, env_config(c.task, c.rl.env_kwargs))
        for c in configs
    )
    check_fits(
        need * at_once, free_memory(configs[0].device), f"{at_once} sweep trials at once",
        "memory", "lower --max-concurrent, the envs per trial (--envs) or the patients",
    )  # fmt: skip


def trial_name(task: str, algo: str, params: dict[str, Any]) -> str:
    parts = [f"{k}={v}" for k, v in sorted(params.items()) if k != "seed"]
    return "-".join([task, algo, *parts, f"s{params.get('seed', 0)}"]).replace("/", "_")


def sweep(
    task: str,
    algo: str,
    out: str | Path,
    seeds: int = 3,
    grid: dict[str, list[Any]] | None = None,
    samples: int = 1,
    address: str | None = None,
    max_concurrent: int | None = None,
    resume: bool = False,
    force: bool = False,
    log: Callable[[str], None] = print,
    **train_options: Any,
) -> SweepResult:
    """Run the sweep (see the module doc). ``train_options``: ``resolve_train_config``'s
    (``preset``, ``envs``, ``steps``, ``device``, ``env_kwargs``, ...), for every trial.
    ``max_concurrent``: trials running at once (None: as many as the CPUs/GPUs hold). The sweep
    folder is locked while the sweep runs (``sonogym.runs.prepare_output``)."""
    import_ray()
    out = Path(out).resolve()
    if resume:
        spec = read_json(out / SWEEP_FILE, "sonogym sweep", ("base", "grid", "seeds"))
    else:
        if seeds < 1 or samples < 1:
            raise ValueError(f"seeds and samples must be >= 1, got {seeds} and {samples}")
        grid = {k: list(v) for k, v in (grid or {}).items()}
        for k in grid:
            check_key(k)
        base = resolve_train_config(task, algo, **train_options)
        configs = []
        for values in _grid_points(grid):  # every trial's config must be valid up front
            try:
                configs.append(apply(base, values))
            except ValueError as e:
                raise ValueError(f"grid point {values}: {e}; change --grid") from None
        check_sweep_memory(configs, len(configs) * seeds * samples, max_concurrent)
        spec = {"base": base.to_dict(), "grid": grid, "seeds": seeds, "samples": samples}
    with prepare_output(out, resume=resume, force=force, kind="sweep") as folder:
        if folder.deleted:
            log(deleted_message(out, folder.deleted))
        if not resume:
            atomic_write_json(out / SWEEP_FILE, spec)
        return _run_sweep(out, spec, address, max_concurrent, resume, log)


def _run_sweep(out: Path, spec: dict, address, max_concurrent, resume: bool, log) -> SweepResult:
    ray, tune = import_ray()
    base = TrainConfig.from_dict(spec["base"])
    resources = {"cpu": base.threads or 1}
    if str(base.device).startswith("cuda"):
        resources["gpu"] = 1.0 / max(1, int(spec.get("trials_per_gpu", 2)))
    trainable = tune.with_resources(_trial, resources)
    if not ray.is_initialized():
        if address:
            ray.init(address=address)
        else:
            ray.init(include_dashboard=False, log_to_driver=False)
    try:
        if resume:
            tuner = tune.Tuner.restore(str(out / "tune"), trainable, resume_errored=False)
        else:
            space = {"_base": spec["base"], "_root": str(out / "runs"),
                     "seed": tune.grid_search(list(range(spec["seeds"])))}  # fmt: skip
            space.update({k: tune.grid_search(v) for k, v in spec["grid"].items()})
            tuner = tune.Tuner(
                trainable,
                param_space=space,
                tune_config=tune.TuneConfig(
                    num_samples=spec["samples"], max_concurrent_trials=max_concurrent
                ),
                run_config=tune.RunConfig(
                    name="tune",
                    storage_path=str(out),
                    failure_config=tune.FailureConfig(max_failures=0, fail_fast=False),
                    verbose=0,
                ),
            )
        results = tuner.fit()
    finally:
        if not address:
            ray.shutdown()
    rows = []
    for r in results:
        params = {k: v for k, v in _trial_config(r).items() if not k.startswith("_")}
        metrics = {k: v for k, v in (r.metrics or {}).items() if _is_metric(k, v)}
        error = None if r.error is None else str(r.error).splitlines()[-1][:300]
        name = trial_name(base.task, base.algo, params)
        rows.append(TrialRow(name, params, "ERROR" if error else "TERMINATED", metrics, error))
    rows.sort(key=lambda row: row.name)
    _write_table(out, rows)
    log(f"wrote {out / 'sweep.md'} ({len(rows)} trials, "
        f"{sum(r.status == 'ERROR' for r in rows)} errored); runs in {out / 'runs'}")  # fmt: skip
    return SweepResult(out, tuple(rows))


def _trial(config: dict[str, Any]) -> None:
    """One trial (runs in a Ray worker): train, reporting at each checkpoint."""
    from ray import tune

    from sonogym.agents.train import run_training

    params = {k: v for k, v in config.items() if not k.startswith("_")}
    cfg = apply(TrainConfig.from_dict(config["_base"]), params)
    run = Path(config["_root"]) / trial_name(cfg.task, cfg.algo, params)
    resume = (run / "config.json").is_file() and any((run / "checkpoints").glob("agent_*.pt"))

    def report(steps: int, checkpoint: Path, metrics: dict[str, float]) -> None:
        with tempfile.TemporaryDirectory() as d:
            shutil.copy2(checkpoint, Path(d) / checkpoint.name)
            tune.report({"steps": steps, "run": str(run), **metrics},
                        checkpoint=tune.Checkpoint.from_directory(d))  # fmt: skip

    run_training(cfg, run, resume=resume, force=run.exists() and not resume, progress=False,
                 log=lambda m: None, on_checkpoint=report)  # fmt: skip


def _trial_config(result) -> dict[str, Any]:
    """A trial's config; a restored sweep's errored trials carry none, so read the
    ``params.json`` Tune wrote in the trial's folder."""
    if result.config:
        return result.config
    params = Path(result.path) / "params.json"
    return read_json(params, "Ray Tune trial folder") if params.is_file() else {}


def _grid_points(grid: dict[str, list[Any]]):
    import itertools

    keys = list(grid)
    for combo in itertools.product(*(grid[k] for k in keys)) if keys else [()]:
        yield dict(zip(keys, combo, strict=True))


#: bookkeeping Tune adds to every report (not the trial's metrics)
_TUNE_KEYS = {"timestamp", "time_this_iter_s", "time_total_s", "pid", "time_since_restore",
              "iterations_since_restore", "training_iteration", "done"}  # fmt: skip


def _is_metric(k: str, v: Any) -> bool:
    return k not in _TUNE_KEYS and isinstance(v, int | float) and not isinstance(v, bool)


def _write_table(out: Path, rows: list[TrialRow]) -> None:
    params = sorted({k for r in rows for k in r.params})
    metrics = sorted({k for r in rows for k in r.metrics})
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(["trial", *params, "status", *metrics, "error"])
    for r in rows:
        w.writerow([r.name, *(r.params.get(k) for k in params), r.status,
                    *(r.metrics.get(k) for k in metrics), r.error or ""])  # fmt: skip
    atomic_write_text(out / "sweep.csv", buf.getvalue())
    head = ["trial", *params, "status", *metrics]
    md = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    for r in rows:
        cells = [r.name, *(str(r.params.get(k)) for k in params), r.status]
        cells += [f"{r.metrics[k]:.4g}" if k in r.metrics else "-" for k in metrics]
        md.append("| " + " | ".join(cells) + " |")
    for r in rows:
        if r.error:
            md.append(f"\n{r.name} failed: {r.error}")
    atomic_write_text(out / "sweep.md", "\n".join(md) + "\n")
