import os
import pickle
import subprocess
import sys

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from sonogym.anatomy import PhantomParams, load_phantom, load_totalsegmentator
from sonogym.anatomy.phantom import phantom_cache_key
from sonogym.cli import app


def test_phantom_cache_round_trip_and_key(tmp_path, monkeypatch):
    monkeypatch.setenv("SONOGYM_CACHE", str(tmp_path))
    params = PhantomParams(spacing=0.002)
    a = load_phantom(7, params)
    files = sorted(p.suffix for p in tmp_path.glob("phantom-7-*"))
    assert files == [".json", ".npz"]  # arrays + sidecar, no temporary left behind
    b = load_phantom(7, params)
    assert torch.equal(a.ct, b.ct) and torch.equal(a.labels, b.labels)
    assert np.array_equal(a.affine, b.affine) and b.meta["params"] == a.meta["params"]
    assert phantom_cache_key(7, params) != phantom_cache_key(8, params)
    assert phantom_cache_key(7, params) != phantom_cache_key(
        7, PhantomParams(spacing=0.002, fat_thickness=0.01)
    )
    with np.load(next(tmp_path.glob("*.npz")), allow_pickle=False) as z:  # plain arrays
        assert sorted(z.files) == ["ct", "labels"] and z["ct"].dtype == np.int16


def test_corrupt_cache_entry_is_reported_and_rebuilt(tmp_path, monkeypatch):
    monkeypatch.setenv("SONOGYM_CACHE", str(tmp_path))
    params = PhantomParams(spacing=0.002)
    a = load_phantom(7, params)
    npz = next(tmp_path.glob("phantom-7-*.npz"))
    data = bytearray(npz.read_bytes())
    data[len(data) // 2] ^= 0xFF  # one flipped byte in the middle of the CT
    npz.write_bytes(bytes(data))
    with pytest.warns(RuntimeWarning, match=f"{npz.stem}.*corrupt.*rebuilding"):
        c = load_phantom(7, params)
    assert torch.equal(a.ct, c.ct) and torch.equal(a.labels, c.labels)
    assert npz.read_bytes() != bytes(data)  # rewritten
    side = npz.with_suffix(".json")
    side.write_text(side.read_text().replace('"phantom-7"', '"phantom-8"'))  # tampered sidecar
    with pytest.warns(RuntimeWarning, match="checksum"):
        assert load_phantom(7, params).name == "phantom-7"


def test_cache_never_unpickles_and_cleans_dead_writers(tmp_path, monkeypatch):
    monkeypatch.setenv("SONOGYM_CACHE", str(tmp_path))
    params = PhantomParams(spacing=0.002)
    stem = f"phantom-7-{phantom_cache_key(7, params)}"
    marker = tmp_path / "pwned"

    class Payload:
        def __reduce__(self):
            return (open, (str(marker), "w"))

    # A planted entry in the old pickle format (and a pickle under the new name) never runs.
    (tmp_path / f"{stem}.pt").write_bytes(pickle.dumps({"ct": Payload()}))
    (tmp_path / f"{stem}.npz").write_bytes(pickle.dumps(Payload()))
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    stale = tmp_path / f"{stem}.npz.tmp{dead.pid}"
    live = tmp_path / f"{stem}.json.tmp{os.getppid()}"  # a writer that is still running
    stale.write_bytes(b"half")
    live.write_bytes(b"half")
    with pytest.warns(RuntimeWarning, match="corrupt"):
        p = load_phantom(7, params)
    assert p.has("L4") and not marker.exists()
    assert not stale.exists() and live.exists()
    assert not (tmp_path / f"{stem}.pt").exists()  # the old entry is replaced


def test_phantom_command_writes_layout_and_preview(tmp_path, monkeypatch):
    monkeypatch.setenv("SONOGYM_CACHE", str(tmp_path / "cache"))
    out = tmp_path / "p"
    res = CliRunner().invoke(app, ["phantom", "--seed", "1", "--spacing", "2", "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert (out / "preview.png").stat().st_size > 10_000
    p = load_totalsegmentator(out, spacing=None, target="L4")
    assert p.name == "p" and p.has("vertebrae_L4")


def test_help_lists_subcommands():
    res = CliRunner().invoke(app, ["--help"])
    assert res.exit_code == 0 and "phantom" in res.output
