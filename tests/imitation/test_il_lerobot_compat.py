"""LeRobot's own reader opens our datasets with equal values (needs a LeRobot venv).

Runs ``scripts/check_lerobot_compat.py`` when SONOGYM_LEROBOT_PYTHON names the python of a venv
with ``lerobot-dataset`` (set-up: the script's header); skipped otherwise. The behaviour it
checks is also pinned, without LeRobot, by test_il_dataset.py against our own reader.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

LEROBOT_PYTHON = os.environ.get("SONOGYM_LEROBOT_PYTHON")
ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.skipif(
    not LEROBOT_PYTHON, reason="set SONOGYM_LEROBOT_PYTHON to a venv python with lerobot-dataset"
)
def test_lerobot_reads_our_dataset_with_equal_values():
    env = {**os.environ, "PYTHONPATH": str(ROOT / "src")}
    r = subprocess.run(
        [
            sys.executable,
            str(ROOT / "scripts/check_lerobot_compat.py"),
            "--lerobot-python",
            LEROBOT_PYTHON,
        ],
        capture_output=True,
        text=True,
        env=env,
        timeout=600,
    )
    assert r.returncode == 0, r.stdout + r.stderr
    assert "all values equal" in r.stdout and "codebase v3.0" in r.stdout
