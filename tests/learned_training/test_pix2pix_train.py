"""pix2pix training on a tiny simulated dataset, its checkpoint, and the CLI wrappers."""

import json

import pytest
import torch
from typer.testing import CliRunner

from sonogym.cli import app
from sonogym.learned_training.data import write_default_pairs
from sonogym.learned_training.train import train_pix2pix
from sonogym.ultrasound.learned.checkpoint import load_generator

torch.set_num_threads(1)

TINY = dict(image_size=(32, 32), pixel_spacing=2e-3, phantom_spacing=2e-3, models_per_seed=2)


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    out = tmp_path_factory.mktemp("pairs")
    write_default_pairs(out, n=16, seeds=[1000], test_fraction=0.25, **TINY)
    return out


def test_training_lowers_l1_and_writes_files(tiny, tmp_path):
    m = train_pix2pix(
        tiny, tmp_path, seed=0, steps=60, width=8, depth=3, disc_width=8, batch_size=8,
        lr=2e-3, eval_every=30, progress=False,
    )  # fmt: skip
    assert m["train_l1_last"] < 0.85 * m["train_l1_first"], m
    assert m["test"]["n"] == 4
    assert 0 < m["test"]["ssim"] <= 1 and m["test"]["psnr"] > 5
    assert len(m["test_history"]) == 2
    assert m["lpips"] is None and "offline" in m["lpips_note"]
    assert json.loads((tmp_path / "metrics.json").read_text())["steps"] == 60
    assert list((tmp_path / "tb").glob("events.out.tfevents.*"))
    assert len((tmp_path / "losses.jsonl").read_text().splitlines()) == 60
    gen, hist, meta = load_generator(tmp_path / "generator.pt")
    assert meta["input_size"] == [32, 32] and meta["seed"] == 0
    assert gen.config.channels == (8, 16, 32, 32)
    with torch.no_grad():
        y = gen(hist.match(torch.rand(2, 1, 32, 32)))
    assert y.shape == (2, 1, 32, 32)


def test_training_is_seeded(tiny, tmp_path):
    kw = dict(steps=3, width=8, depth=3, disc_width=8, progress=False, tensorboard=False)
    a = train_pix2pix(tiny, tmp_path / "a", seed=1, **kw)
    b = train_pix2pix(tiny, tmp_path / "b", seed=1, **kw)
    assert a["train_l1_last"] == b["train_l1_last"]


def test_load_generator_rejects_other_files(tmp_path):
    torch.save({"x": 1}, tmp_path / "g.pt")
    with pytest.raises(ValueError, match="not a sonogym"):
        load_generator(tmp_path / "g.pt")


def test_cli_lb_data_and_lb_train(tmp_path):
    runner = CliRunner()
    data, run = tmp_path / "data", tmp_path / "run"
    r = runner.invoke(
        app,
        ["lb-data", "--out", str(data), "--pairs", "8", "--seed", "1000", "--phantoms", "1",
         "--size", "32", "--pixel-mm", "2", "--phantom-mm", "2"],
    )  # fmt: skip
    assert r.exit_code == 0, r.output
    assert (data / "manifest.json").is_file()
    r = runner.invoke(
        app,
        ["lb-train", "--data", str(data), "--seed", "0", "--out", str(run), "--steps", "2",
         "--width", "8", "--depth", "3", "--no-progress"],
    )  # fmt: skip
    assert r.exit_code == 0, r.output
    assert (run / "generator.pt").is_file() and (run / "metrics.json").is_file()
    assert "SSIM" in r.output
