"""Shared fixtures: one small (2 mm) phantom per test session keeps the suite fast."""

from __future__ import annotations

import os

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
