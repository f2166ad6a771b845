"""Paired CT/US data: default pairs from the physical model, the manifest and the reader."""

import json

import numpy as np
import pytest
import torch

from sonogym.learned_training.data import (
    PairedDataError,
    PairedDataset,
    random_physical_model,
    read_manifest,
    write_default_pairs,
)
from sonogym.ultrasound.learned.histogram import CT_WINDOW_HU

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    out = tmp_path_factory.mktemp("pairs")
    write_default_pairs(
        out, n=16, seeds=[1000, 1001], image_size=(32, 32), pixel_spacing=2e-3,
        phantom_spacing=2e-3, models_per_seed=2, test_fraction=0.25,
    )  # fmt: skip
    return out


def test_default_pairs_write_and_read_back(tiny):
    m = read_manifest(tiny)
    assert m["version"] == 1 and m["image_size"] == [32, 32]
    assert m["ct_window_hu"] == list(CT_WINDOW_HU)
    assert m["source"]["phantom_seeds"] == [1000, 1001]
    assert len(m["pairs"]) == 16
    train, test = PairedDataset(tiny, "train"), PairedDataset(tiny, "test")
    assert (len(train), len(test)) == (12, 4)
    ct, us = train[0]
    assert ct.shape == us.shape == (1, 32, 32) and ct.dtype == us.dtype == torch.float32
    assert 0 <= float(ct.min()) and float(ct.max()) <= 1
    assert 0 <= float(us.min()) and float(us.max()) <= 1
    # raw files: CT in HU clamped to the window, US not blank and not constant
    with np.load(tiny / m["pairs"][0]["ct"]) as z:
        assert z["ct"].min() >= CT_WINDOW_HU[0] and z["ct"].max() <= CT_WINDOW_HU[1]
    assert train.us.std() > 0.05 and train.ct.std() > 0.02
    # pairs differ from each other (random poses)
    assert (train.ct[0] - train.ct[1]).abs().mean() > 0


def test_manifests_name_the_ultrasound_model_and_older_ones_still_read(tiny, tmp_path):
    assert read_manifest(tiny)["source"]["us_model"].startswith("physical")
    old = json.loads((tiny / "manifest.json").read_text())
    old["source"]["preset"] = old["source"].pop("us_model")  # as written before the rename
    (tmp_path / "manifest.json").write_text(json.dumps(old))
    source = read_manifest(tmp_path)["source"]
    assert source["us_model"].startswith("physical") and "preset" not in source


def test_random_physical_models_differ():
    rng = np.random.default_rng(0)
    a, b = random_physical_model(rng), random_physical_model(rng)
    assert a.gain != b.gain and a.f_number != b.f_number
    assert a.tissues.params(1).alpha != b.tissues.params(1).alpha


def test_reader_errors(tmp_path, tiny):
    with pytest.raises(PairedDataError, match="no manifest"):
        PairedDataset(tmp_path)
    m = read_manifest(tiny)
    bad = tmp_path / "bad"
    (bad / "pairs").mkdir(parents=True)
    m["pairs"] = [{"ct": "pairs/a.npz", "us": "pairs/a.npz", "split": "train"}]
    (bad / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(PairedDataError, match="missing pair file"):
        PairedDataset(bad)
    np.savez(bad / "pairs/a.npz", ct=np.zeros((8, 8), np.float32), us=np.zeros((8, 6), np.float32))
    with pytest.raises(PairedDataError, match="equal 2-D shapes"):
        PairedDataset(bad)
    m["pairs"][0]["split"] = "val"
    (bad / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(PairedDataError, match="split"):
        PairedDataset(bad)


def test_separate_ct_and_us_files(tmp_path):
    """Real data: CT and US as separate .npy files."""
    (tmp_path / "ct").mkdir()
    (tmp_path / "us").mkdir()
    pairs = []
    for i in range(3):
        np.save(tmp_path / f"ct/{i}.npy", np.full((16, 16), 100.0 * i, np.float32))
        np.save(tmp_path / f"us/{i}.npy", np.full((16, 16), 0.1 * i, np.float32))
        pairs.append({"ct": f"ct/{i}.npy", "us": f"us/{i}.npy", "split": "train"})
    manifest = {"version": 1, "pixel_spacing_m": [3e-4, 3e-4], "ct_window_hu": [0, 1000]}
    (tmp_path / "manifest.json").write_text(json.dumps({**manifest, "pairs": pairs}))
    ds = PairedDataset(tmp_path)
    assert len(ds) == 3 and float(ds[2][0].mean()) == pytest.approx(0.2)
    assert float(ds[2][1].mean()) == pytest.approx(0.2)
