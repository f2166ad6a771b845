"""Shared fixtures: one small (2 mm) phantom per test session keeps the suite fast."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

# One intra-op thread per xdist worker: two workers on two cores, no oversubscription.
if os.environ.get("PYTEST_XDIST_WORKER"):
    torch.set_num_threads(1)

from sonogym.anatomy import Patient, PhantomParams, make_phantom

SMALL = PhantomParams(spacing=0.002)


@pytest.fixture(scope="session", autouse=True)
def _isolated_cache(tmp_path_factory):
    """Phantoms built by tests go to a per-session cache, not the user's."""
    old = os.environ.get("SONOGYM_CACHE")
    os.environ["SONOGYM_CACHE"] = str(tmp_path_factory.mktemp("sonogym-cache"))
    yield
    if old is None:
        os.environ.pop("SONOGYM_CACHE", None)
    else:
        os.environ["SONOGYM_CACHE"] = old


@pytest.fixture(scope="session")
def small_phantom() -> Patient:
    """Seed-0 phantom at 2 mm (built once per test process)."""
    return make_phantom(0, SMALL)


_HOLD = (
    "import sys, time\n"
    "from sonogym.runs import prepare_output\n"
    "prepare_output(sys.argv[1], resume=False, force=False, kind=sys.argv[2])\n"
    "print('holding', flush=True)\n"
    "time.sleep(300)\n"
)


@pytest.fixture
def folder_in_use():
    """``start(folder, kind)``: another process prepares (and so locks) an output folder, as a
    running command does, and keeps running until the test ends; returns its ``Popen``."""
    procs = []
    src = str(Path(__file__).resolve().parents[1] / "src")

    def start(folder, kind: str) -> subprocess.Popen:
        p = subprocess.Popen(
            [sys.executable, "-c", _HOLD, str(folder), kind], stdout=subprocess.PIPE, text=True,
            env={**os.environ, "PYTHONPATH": src},
        )  # fmt: skip
        procs.append(p)
        assert p.stdout.readline().strip() == "holding"
        return p

    yield start
    for p in procs:
        p.kill()
        p.wait()
