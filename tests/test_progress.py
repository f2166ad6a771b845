"""Progress in a log: plain newline-terminated lines every few percent or every 30 s, not a
redrawn bar."""

from __future__ import annotations

import io

from sonogym.progress import PERCENT, SECONDS, PlainProgress, progress_bar


class _Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def test_a_line_every_few_percent_and_one_at_the_end():
    out = io.StringIO()
    bar = PlainProgress(1000, "train", unit="step", stream=out, clock=_Clock())
    for _ in range(1000):
        bar.update(1)
    bar.close()
    lines = out.getvalue().splitlines()
    assert len(lines) == 100 // PERCENT  # 50, 100, ..., 1000
    assert lines[0].startswith("train: 50/1000 step (5%)")
    assert lines[-1].startswith("train: 1000/1000 step (100%)")
    assert "\r" not in out.getvalue() and out.getvalue().endswith("\n")


def test_a_slow_loop_gets_a_line_every_30_s_and_a_resumed_one_counts_from_its_start():
    out, clock = io.StringIO(), _Clock()
    bar = PlainProgress(10_000, "il-train act", initial=2_000, unit="step", stream=out,
                        clock=clock)  # fmt: skip
    for _ in range(30):  # 30 steps of 10 s each: 0.3 % of the total
        clock.t += 10.0
        bar.update(1)
    lines = out.getvalue().splitlines()
    assert len(lines) == 300 // SECONDS
    assert lines[0].startswith("il-train act: 2003/10000 step (20%), 30 s, 0.1 step/s, ETA 22.2 h")
    bar.set_postfix(loss="0.1234")
    clock.t += 1.0
    bar.update(1)  # too soon for a line; close writes where it stopped
    bar.close()
    lines = out.getvalue().splitlines()
    assert len(lines) == 300 // SECONDS + 1
    assert lines[-1].startswith("il-train act: 2031/10000") and lines[-1].endswith("loss=0.1234")


def test_a_terminal_gets_a_tqdm_bar_and_a_log_plain_lines():
    class Terminal(io.StringIO):
        def isatty(self) -> bool:
            return True

    assert type(progress_bar(10, "x", stream=Terminal())).__name__ == "tqdm"
    log = io.StringIO()
    assert isinstance(progress_bar(10, "x", stream=log), PlainProgress)
    quiet = progress_bar(10, "x", enabled=False, stream=log)
    quiet.update(10)
    quiet.close()
    assert log.getvalue() == ""
