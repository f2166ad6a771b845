"""Fixtures of the imitation tests; their data comes from il_datasets."""

from __future__ import annotations

import pytest
from il_datasets import BLOB_FEATURES, FPS, blob_episodes

from sonogym.imitation.writer import DatasetWriter


@pytest.fixture(scope="session")
def blob_dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("blob") / "ds"
    with DatasetWriter(root, FPS, BLOB_FEATURES, task="reach the centre") as w:
        for ep in blob_episodes(8):
            w.add_episode(ep)
    return root
