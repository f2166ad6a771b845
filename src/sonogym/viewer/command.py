"""``sonogym view``: pick the source (an env under a policy, a run's saved episode, a dataset's
episode), log it, and save the recording or serve it to the web viewer."""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from sonogym.viewer.env_view import ViewResult, policy_choice, resolve_env, view_env
from sonogym.viewer.replay import view_dataset_episode, view_run_episode
from sonogym.viewer.session import open_session, serve_until_interrupted

#: Where a view is saved when neither a file nor the web viewer is asked for.
DEFAULT_DIR = Path("runs/view")


@dataclass(frozen=True)
class ViewRequest:
    """One of: ``task`` and/or ``policy``/``pretrained`` (step an env), ``run`` (replay its
    ``protocol`` log's ``episode``), ``dataset`` (replay its ``episode``)."""

    task: str | None = None
    policy: str = "expert"
    pretrained: str | None = None
    env_options: dict[str, Any] = field(default_factory=dict)
    steps: int | None = None
    seed: int = 0  # the env's reset seed
    run: Path | None = None
    protocol: str = "idt"
    controller: str | None = None
    dataset: Path | None = None
    episode: int = 0

    @property
    def name(self) -> str:
        """A file-name-safe name of what is viewed."""
        if self.run is not None:
            raw = f"{self.run.resolve().name}-{self.protocol}-ep{self.episode}"
        elif self.dataset is not None:
            raw = f"{self.dataset.resolve().name}-ep{self.episode}"
        else:
            who = self.pretrained or Path(self.policy).name
            raw = f"{self.task or 'run'}-{who}"
        return re.sub(r"[^A-Za-z0-9_.-]+", "_", raw)


def _metrics_text(metrics: dict[str, float]) -> str:
    return ", ".join(f"{k} {v:.3g}" for k, v in metrics.items())


def run_view(
    req: ViewRequest,
    save: str | Path | None = None,
    web: bool = False,
    web_port: int = 9090,
    log: Callable[[str], None] = print,
) -> ViewResult:
    """Log ``req``'s source to ``save`` (default ``runs/view/<name>.rrd``) or, with ``web``,
    serve it on ``localhost:web_port`` until Ctrl-C (the gRPC stream on the next port)."""
    if req.run is not None and req.dataset is not None:
        raise ValueError("give --run or --dataset, not both")
    if save is not None and web:
        raise ValueError("give --save FILE.rrd or --web, not both")
    if req.episode < 0:
        raise ValueError(f"--episode must be >= 0, got {req.episode}")
    env_mode = req.run is None and req.dataset is None
    if env_mode:  # resolve before anything is opened: bad input fails with nothing written
        choice = policy_choice(req.policy, req.pretrained)
        task, options = resolve_env(req.task, choice, req.env_options)
    if save is None and not web:
        save = DEFAULT_DIR / f"{req.name}.rrd"
    session = open_session(req.name, save, web, web_port, web_port + 1)
    if web:
        log(f"web viewer: {session.url}")
    if req.run is not None:
        result = view_run_episode(
            session.rec, req.run, req.protocol, req.episode, req.controller, log
        )
    elif req.dataset is not None:
        result = view_dataset_episode(session.rec, req.dataset, req.episode, log)
    else:
        result = view_env(session.rec, task, choice, options, req.steps, req.seed, log)
        for k, m in enumerate(result.episodes):
            log(f"episode {k} ended: {_metrics_text(m)}")
        log(f"after step {result.timeline - 1}: {_metrics_text(result.last)}")
    if web:
        serve_until_interrupted(session, log)
    else:
        session.close()
        size = session.path.stat().st_size / 2**20
        log(
            f"wrote {session.path} ({size:.1f} MiB, step 0..{result.timeline - 1}); "
            f"open it with: rerun {session.path}"
        )
    return result
