import torch
from typer.testing import CliRunner

from sonogym.anatomy import PhantomParams, load_phantom, load_totalsegmentator
from sonogym.anatomy.phantom import phantom_cache_key
from sonogym.cli import app


def test_phantom_cache_round_trip_and_key(tmp_path, monkeypatch):
    monkeypatch.setenv("SONOGYM_CACHE", str(tmp_path))
    params = PhantomParams(spacing=0.002)
    a = load_phantom(7, params)
    files = list(tmp_path.glob("phantom-7-*.pt"))
    assert len(files) == 1
    b = load_phantom(7, params)
    assert torch.equal(a.ct, b.ct) and torch.equal(a.labels, b.labels)
    assert phantom_cache_key(7, params) != phantom_cache_key(8, params)
    assert phantom_cache_key(7, params) != phantom_cache_key(
        7, PhantomParams(spacing=0.002, fat_thickness=0.01)
    )
    files[0].write_bytes(b"corrupt")
    c = load_phantom(7, params)  # a broken cache entry is rebuilt, not fatal
    assert torch.equal(a.labels, c.labels)


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
