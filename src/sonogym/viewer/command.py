"""``sonogym view``: pick the source (an env under a policy, a run's saved episode, a dataset's
episode), log it, and save the recording (complete, or not at all) or serve it to the web
viewer."""

from __future__ import annotations

import os
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from sonogym.outputs import check_file, undo_on_failure
from sonogym.viewer.env_view import ViewResult, policy_choice, resolve_env, view_env
from sonogym.viewer.replay import load_run_log, view_dataset_episode, view_run_episode
from sonogym.viewer.session import is_sonogym_recording, open_session, serve_until_interrupted

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
    force: bool = False,
    progress: bool = False,
) -> ViewResult:
    """Log ``req``'s source to ``save`` (default ``runs/view/<name>.rrd``) or, with ``web``,
    serve it on ``localhost:web_port`` until Ctrl-C (the gRPC stream on the next port).

    The source is checked before any file is opened. The recording is written beside ``save``
    under a temporary name and renamed over it only when complete, so a view that fails (or is
    interrupted) leaves ``save`` as it was and no file of its own; an existing ``save`` that is
    not a sonogym recording is refused unless ``force``. ``progress``: show the env's patients
    loading and the steps on stderr."""
    if req.run is not None and req.dataset is not None:
        raise ValueError("give --run or --dataset, not both")
    if save is not None and web:
        raise ValueError("give --save FILE.rrd or --web, not both")
    if req.episode < 0:
        raise ValueError(f"--episode must be >= 0, got {req.episode}")
    env_mode = req.run is None and req.dataset is None
    source = None
    if env_mode:  # resolve before anything is opened: bad input fails with nothing written
        choice = policy_choice(req.policy, req.pretrained)
        source = (choice, *resolve_env(req.task, choice, req.env_options))
    elif req.run is not None:
        load_run_log(req.run, req.protocol)  # a missing log is named before anything is opened
    if web:
        session = open_session(req.name, None, True, web_port, web_port + 1)
        log(f"web viewer: {session.url}")
        result = _log_source(session, req, source, log, progress)
        serve_until_interrupted(session, log)
        return result
    target = check_view_file(DEFAULT_DIR / f"{req.name}.rrd" if save is None else save, force)
    partial = target.with_name(f".{target.stem}.{os.getpid()}.partial.rrd")
    kept = f"{target} was left as it was" if target.exists() else ""
    with undo_on_failure(target, temporary=(partial,), kept=kept):
        session = open_session(req.name, partial)
        result = _log_source(session, req, source, log, progress)
        session.close()
        os.replace(partial, target)
    size = target.stat().st_size / 2**20
    log(
        f"wrote {target} ({size:.1f} MiB, step 0..{result.timeline - 1}); "
        f"open it with: rerun {target}"
    )
    return result


def check_view_file(path: str | Path, force: bool = False) -> Path:
    """``path`` as the .rrd file a view is saved to (``sonogym.outputs.check_file``): an .rrd
    name in a folder that can be written; an existing file that is not a sonogym recording
    is refused unless ``force``."""
    path = Path(path)
    if path.suffix != ".rrd":
        raise ValueError(f"{path}: a Rerun recording is saved as an .rrd file")
    return check_file(path, "view file", force=force, ours=is_sonogym_recording)


def _log_source(session, req: ViewRequest, source, log, progress: bool) -> ViewResult:
    """Log the request's source (an env under a policy, a run's episode, a dataset's
    episode) into the session's recording."""
    if req.run is not None:
        return view_run_episode(
            session.rec, req.run, req.protocol, req.episode, req.controller, log
        )
    if req.dataset is not None:
        return view_dataset_episode(session.rec, req.dataset, req.episode, log)
    choice, task, options = source
    result = view_env(session.rec, task, choice, options, req.steps, req.seed, log, progress)
    for k, m in enumerate(result.episodes):
        log(f"episode {k} ended: {_metrics_text(m)}")
    log(f"after step {result.timeline - 1}: {_metrics_text(result.last)}")
    return result
