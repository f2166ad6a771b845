"""Progress of long loops (training, recording, data generation, evaluation, loading an env's
patients): a tqdm bar on a terminal, plain lines in a log.

A tqdm bar redraws itself with carriage returns, which a terminal shows as one changing line
but a log file keeps whole: with output redirected, a 45-s training run wrote ~1,800 updates
onto one line. ``progress_bar`` gives tqdm when stderr is a terminal, and otherwise a
``PlainProgress``: a newline-terminated line every ``PERCENT`` % of the total or every
``SECONDS`` s, whichever comes first, and one at the end.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable
from typing import Any, TextIO

PERCENT = 5  # a plain line at least every this many percent of the total
SECONDS = 30.0  # ... and at least this often (s) while the loop advances


def progress_bar(
    total: int,
    desc: str,
    initial: int = 0,
    unit: str = "it",
    enabled: bool = True,
    stream: TextIO | None = None,
):
    """A progress display with tqdm's ``update(n)``, ``set_postfix(**values)`` and ``close()``:
    tqdm on a terminal ``stream`` (default stderr), ``PlainProgress`` elsewhere, nothing when
    not ``enabled``."""
    stream = sys.stderr if stream is None else stream
    if not enabled:
        return PlainProgress(total, desc, initial, unit, stream, enabled=False)
    isatty = getattr(stream, "isatty", None)
    if isatty is not None and isatty():
        from tqdm import tqdm

        return tqdm(total=total, initial=initial, desc=desc, unit=unit, file=stream)
    return PlainProgress(total, desc, initial, unit, stream)


def announce(line: str, enabled: bool = True, stream: TextIO | None = None) -> None:
    """One line saying what a long step is about to do, where its progress goes (stderr)."""
    if enabled:
        stream = sys.stderr if stream is None else stream
        stream.write(line + "\n")
        stream.flush()


class PlainProgress:
    """Progress as plain lines, e.g. ``navigation/ppo: 160/3200 step (5%), 12 s, 13.3 step/s,
    ETA 3.8 min, loss=0.12`` (see the module doc)."""

    def __init__(
        self,
        total: int,
        desc: str,
        initial: int = 0,
        unit: str = "it",
        stream: TextIO | None = None,
        enabled: bool = True,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.total, self.desc, self.unit = int(total), desc, unit
        self.clock = clock
        self.n = self._start = self._shown = int(initial)
        self.stream = sys.stderr if stream is None else stream
        self.enabled = enabled
        self._every = max(1, math.ceil(self.total * PERCENT / 100))
        self._t0 = self._last = clock()
        self._postfix = ""

    def update(self, n: int = 1) -> None:
        self.n += n
        if not self.enabled:
            return
        now = self.clock()
        crossed = self.n // self._every > self._shown // self._every
        if crossed or now - self._last >= SECONDS or (self.n >= self.total > self._shown):
            self._emit(now)

    def set_postfix(self, **values: Any) -> None:
        self._postfix = ", ".join(f"{k}={v}" for k, v in values.items())

    def close(self) -> None:
        if self.enabled and self.n != self._shown:
            self._emit(self.clock())
        self.enabled = False

    def _emit(self, now: float) -> None:
        elapsed = now - self._t0
        rate = (self.n - self._start) / elapsed if elapsed > 0 else 0.0
        pct = f" ({100 * self.n / self.total:.0f}%)" if self.total else ""
        parts = [f"{self.desc}: {self.n}/{self.total} {self.unit}{pct}", f"{elapsed:.0f} s"]
        if rate > 0:
            parts.append(f"{rate:.3g} {self.unit}/s")
            if self.n < self.total:
                parts.append(f"ETA {_duration((self.total - self.n) / rate)}")
        if self._postfix:
            parts.append(self._postfix)
        self.stream.write(", ".join(parts) + "\n")
        self.stream.flush()
        self._shown, self._last = self.n, now


def _duration(seconds: float) -> str:
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 5400:
        return f"{seconds / 60:.1f} min"
    return f"{seconds / 3600:.1f} h"
