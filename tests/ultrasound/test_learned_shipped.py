"""Shipped learned nets: they load, give images in [0, 1] of the right shape, stay small; net
specs resolve with clear errors; the bone-surface F1 and the linear baseline."""

from dataclasses import replace

import pytest
import torch

from sonogym.anatomy.labels import BONE_IDS
from sonogym.learned_training.model_card import (
    LinearBaseline,
    bone_surface_f1,
    bone_surface_rows,
    detect_surface_rows,
    surface_f1,
)
from sonogym.ultrasound import ProbeGeometry, Slicer
from sonogym.ultrasound.learned.shipped import (
    NUM_SHIPPED,
    WEIGHTS_DIR,
    resolve_nets,
    shipped_weights,
)
from sonogym.ultrasound.learned.simulator import LearnedSimulator

torch.set_num_threads(1)
BONE = min(BONE_IDS)


def test_shipped_weights_are_small_and_complete():
    paths = [shipped_weights(k) for k in range(NUM_SHIPPED)]
    total = sum(p.stat().st_size for p in paths)
    assert total <= 25 * 2**20
    assert sorted(p.name for p in WEIGHTS_DIR.glob("*.pt")) == [f"net{k}.pt" for k in range(5)]


@pytest.mark.parametrize(
    "probe", [ProbeGeometry.linear_2d(), ProbeGeometry.volume_3d()], ids=["2d", "3d"]
)
def test_shipped_nets_give_images_in_unit_range(small_phantom, probe):
    c = small_phantom.landmarks.vertebra("L4").centre
    x = torch.tensor([c[0], c[0] + 0.01], dtype=torch.float64)
    z = torch.tensor([c[2], c[2] - 0.02], dtype=torch.float64)
    pos, rot = small_phantom.skin.surface_pose(x, z, torch.full((2,), torch.pi).double())
    s = Slicer(small_phantom, probe)(pos.float(), rot.float())
    sim = LearnedSimulator([shipped_weights(k) for k in range(NUM_SHIPPED)])
    imgs = [sim.simulate(replace(s, net_index=torch.full((2,), k))) for k in range(NUM_SHIPPED)]
    for img in imgs:
        assert img.shape == (2, *probe.shape) and img.dtype == torch.float32
        assert 0 <= float(img.min()) and float(img.max()) <= 1
        assert float(img.std()) > 0.02  # not a flat image
    assert not torch.allclose(imgs[0], imgs[1], atol=1e-3)  # the nets differ


def test_net_specs_resolve_with_clear_errors(tmp_path):
    assert resolve_nets((0, 4)) == [shipped_weights(0), shipped_weights(4)]
    assert resolve_nets(2) == [shipped_weights(2)]
    with pytest.raises(ValueError, match="ships nets 0-4"):
        resolve_nets((7,))
    with pytest.raises(FileNotFoundError, match="generator.pt"):
        resolve_nets((str(tmp_path / "nope.pt"),))
    with pytest.raises(ValueError, match="empty"):
        resolve_nets(())
    with pytest.raises(TypeError):
        shipped_weights(1.0)


def test_bone_surface_f1_on_a_known_case():
    h, w = 30, 12
    labels = torch.zeros(h, w, dtype=torch.uint8)
    labels[10:, :10] = BONE  # bone from row 10 in columns 0-9; none in 10-11
    assert bone_surface_rows(labels).tolist() == [10] * 10 + [-1, -1]
    img = torch.full((h, w), 0.3)  # tissue
    img[10, :8] = 1.0  # surface echo in columns 0-7
    img[11:, :10] = 0.0  # shadow under the bone
    img[12, 11] = 1.0  # a false surface in column 11 (no bone there)
    img[13:, 11] = 0.0
    rows = detect_surface_rows(img)
    assert rows[:8].tolist() == [10] * 8
    assert rows[11] == 12
    m = bone_surface_f1(img, labels)
    # columns 8-9: shadow but no echo -> the edge at row 10 is 0.3 - 0 >= 0.2: detected too
    assert m["true"] == 10 and m["detected"] == 11 and m["tp"] == 10
    assert m["precision"] == pytest.approx(10 / 11) and m["recall"] == 1.0
    assert m["f1"] == pytest.approx(2 * (10 / 11) / (10 / 11 + 1))
    # tolerance: a detection 4 rows off is a false positive at tol 3, a hit at tol 4
    far = torch.tensor([14, -1])
    true = torch.tensor([10, 10])
    assert surface_f1(far, true, tol_px=3)["tp"] == 0
    assert surface_f1(far, true, tol_px=4)["f1"] == pytest.approx(2 / 3)
    assert surface_f1(torch.tensor([-1]), torch.tensor([-1]))["f1"] == 0.0


def test_linear_baseline_recovers_a_linear_map():
    ct = torch.rand(4, 1, 8, 8)
    base = LinearBaseline.fit(ct, 0.5 * ct + 0.1)
    assert base.a == pytest.approx(0.5, abs=1e-6) and base.b == pytest.approx(0.1, abs=1e-6)
    assert torch.allclose(base(ct), 0.5 * ct + 0.1, atol=1e-6)


def test_bfloat16_precision_keeps_the_images_and_their_bone_surfaces(small_phantom):
    """bfloat16 convolutions (the CPU speed option) change images by ~1e-3 on average and
    leave the detected bone surfaces as they are."""
    c = small_phantom.landmarks.vertebra("L4").centre
    x = torch.linspace(c[0] - 0.02, c[0] + 0.02, 8, dtype=torch.float64)
    z = torch.full_like(x, c[2])
    pos, rot = small_phantom.skin.surface_pose(x, z, torch.zeros_like(x))
    slices = Slicer(small_phantom, ProbeGeometry.linear_2d())(pos.float(), rot.float())
    images = {}
    for precision in ("float32", "bfloat16"):
        sim = LearnedSimulator(shipped_weights(0), precision=precision)
        sim.fit_source(small_phantom.ct)
        images[precision] = sim.simulate(slices)
    a, b = images["float32"], images["bfloat16"]
    assert b.dtype == torch.float32 and b.shape == a.shape
    assert not torch.equal(a, b)  # the option does change the arithmetic
    assert (a - b).abs().mean() < 2e-3
    f1 = [bone_surface_f1(im, slices.labels)["f1"] for im in (a, b)]
    assert f1[1] == pytest.approx(f1[0], abs=0.02)
    with pytest.raises(ValueError, match="precision must be one of"):
        LearnedSimulator(shipped_weights(0), precision="float16")
