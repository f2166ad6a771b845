import math

import matplotlib.image
import pytest
import torch
from typer.testing import CliRunner

from sonogym.cli import app
from sonogym.viz.render import default_poses, parse_pose, render, render_command


def test_parse_pose():
    assert parse_pose("10,-20,3.1416") == pytest.approx((0.01, -0.02, 3.1416, 0.0))
    assert parse_pose(" 1, 2, 1.5, 0.2") == pytest.approx((0.001, 0.002, 1.5, 0.2))
    for bad in ("1,2", "a,b,c", "1,2,3,4,5", "1,nan,2"):
        with pytest.raises(ValueError, match="x,z,yaw"):
            parse_pose(bad)


def test_render_both_models(small_phantom):
    poses = default_poses(small_phantom)
    assert len(poses) == 2 and poses[0][2] == pytest.approx(math.pi)
    r = render(small_phantom, poses, ("physical", "reference"))
    for img in r.images.values():
        assert img.shape == (2, 1, 200, 150) and 0 <= img.min() and img.max() <= 1
        assert img.std() > 0.02
    # the beam reaches bone: some of the image is shadow, some is bright
    phys = r.images["physical"]
    assert (phys > 0.8).float().mean() > 0.0005 and (phys < 0.05).float().mean() > 0.05
    with pytest.raises(ValueError, match="unknown simulator 'fancy'.*physical.*reference"):
        render(small_phantom, poses, ("fancy",))


def test_render_command_writes_pngs_and_sheet(small_phantom, tmp_path):
    paths = render_command(small_phantom, None, "both", False, "volume", tmp_path / "a")
    assert sorted(p.name for p in paths) == [
        "us_0_physical.png",
        "us_0_reference.png",
        "us_1_physical.png",
        "us_1_reference.png",
    ]
    img = matplotlib.image.imread(paths[0])
    assert img.shape[0] == 200  # 50 rows of 2 mm shown at 0.5 mm
    sheet = render_command(
        small_phantom, [(0.0, 0.0, 3.0, 0.1)], "physical", True, "linear", tmp_path
    )
    assert sheet == [tmp_path / "sheet.png"] and sheet[0].stat().st_size > 20_000


def test_image_command(tmp_path, monkeypatch, small_phantom):
    import sonogym.anatomy

    seeds = []

    def fake_load_phantom(seed, params=None):  # the test session's 2 mm phantom, not a fresh build
        seeds.append((seed, params.spacing))
        return small_phantom

    monkeypatch.setattr(sonogym.anatomy, "load_phantom", fake_load_phantom)
    out = tmp_path / "img"
    args = ["image", "--seed", "0", "--spacing", "2", "--pose", "0,0,3.1416", "--out", str(out)]
    res = CliRunner().invoke(app, [*args, "--us-model", "sonogym", "--sheet"])
    assert res.exit_code == 0, res.output
    assert (out / "sheet.png").exists() and "wrote" in res.output
    assert "'sonogym' is now called 'reference'; the old name is removed in 0.3.0" in res.output
    assert seeds == [(0, 0.002)]
    res = CliRunner().invoke(app, ["image", "--pose", "1,2", "--out", str(out)])
    assert res.exit_code != 0 and "x,z,yaw" in res.output
    res = CliRunner().invoke(app, ["image", "--us-model", "fancy", "--seed", "0"])
    assert res.exit_code != 0 and "unknown simulator 'fancy'" in res.output
    res = CliRunner().invoke(app, [*args, "--preset", "physical"])  # the former --us-model
    assert res.exit_code != 0 and "--preset" in res.output


def test_render_is_torch_only_output(small_phantom):
    r = render(small_phantom, [(0.0, 0.0, math.pi, 0.0)])
    assert isinstance(r.images["physical"], torch.Tensor)
