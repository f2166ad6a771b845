"""LearnedSimulator: same interface as ModelBasedSimulator on the same Slices."""

import pytest
import torch

from sonogym.anatomy.phantom import PhantomParams, load_phantom
from sonogym.anatomy.surface import SkinSurface
from sonogym.ultrasound import ModelBasedSimulator, ProbeGeometry, Slicer, UltrasoundSimulator
from sonogym.ultrasound.learned import HistogramReference, UNet, UNetConfig
from sonogym.ultrasound.learned.checkpoint import save_generator
from sonogym.ultrasound.learned.simulator import LearnedSimulator

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def weights(tmp_path_factory):
    d = tmp_path_factory.mktemp("nets")
    hist = HistogramReference.fit(torch.randn(5000) * 300 + 100)
    paths = []
    for s in range(2):
        torch.manual_seed(s)
        gen = UNet(UNetConfig.from_width(8, 3))
        paths.append(save_generator(d / f"g{s}.pt", gen, hist, input_size=[32, 32], seed=s))
    return paths


@pytest.fixture(scope="module")
def slices():
    p = load_phantom(1000, PhantomParams(spacing=2e-3))
    skin = SkinSurface.from_patient(p)
    probe = ProbeGeometry(depth_px=40, width_px=30, elevation_px=2, depth_spacing=2e-3,
                          width_spacing=2e-3, elevation_spacing=4e-3)  # fmt: skip
    n = 5
    pos, rot = skin.surface_pose(
        torch.linspace(-0.03, 0.03, n, dtype=torch.float64),
        torch.linspace(-0.05, 0.05, n, dtype=torch.float64),
        torch.full((n,), torch.pi, dtype=torch.float64),
    )
    return Slicer(p, probe)(pos, rot)


def _render(sim: UltrasoundSimulator, s):
    return sim.simulate(s)


def test_interchangeable_with_model_based(weights, slices):
    sims = [ModelBasedSimulator("physical"), LearnedSimulator(weights[0])]
    for sim in sims:
        assert isinstance(sim, UltrasoundSimulator)
        img = _render(sim, slices)
        assert img.shape == slices.ct.shape == (5, 2, 40, 30)
        assert img.dtype == torch.float32 and img.device == slices.ct.device
        assert 0 <= float(img.min()) and float(img.max()) <= 1


def _subset(s, i, j):
    return type(s)(
        s.ct[i:j], s.labels[i:j], s.origin[i:j], s.row_step[i:j], s.col_step[i:j],
        s.seed[i:j], s.patient_index[i:j], s.probe,
    )  # fmt: skip


@pytest.mark.parametrize("mode", ["first_batch", "per_image", "none"])
def test_deterministic_and_batch_independent(weights, slices, mode):
    sim = LearnedSimulator(weights[0], histogram=mode)
    a = sim.simulate(slices)
    assert torch.equal(a, sim.simulate(slices))
    assert torch.allclose(sim.simulate(_subset(slices, 1, 3)), a[1:3], atol=1e-6)


def test_fit_source_fixes_the_lut(weights, slices):
    a = LearnedSimulator(weights[0])
    a.fit_source(slices.ct)
    b = LearnedSimulator(weights[0])
    b.fit_source(slices.ct)
    # the first call's batch no longer matters
    assert torch.equal(a.simulate(_subset(slices, 0, 2)), b.simulate(slices)[0:2])


def test_random_net_choice(weights, slices):
    sim = LearnedSimulator(weights, seed=0, change_interval=1)
    assert sim.num_nets == 2
    picks = set()
    for _ in range(12):
        sim.simulate(slices)
        picks.add(sim.net_index)
    assert picks == {0, 1}
    again = LearnedSimulator(weights, seed=0, change_interval=1)
    seq = []
    for _ in range(6):
        again.simulate(slices)
        seq.append(again.net_index)
    sim2 = LearnedSimulator(weights, seed=0, change_interval=1)
    assert seq == [(sim2.simulate(slices), sim2.net_index)[1] for _ in range(6)]
    # change_interval: the net stays for that many calls
    slow = LearnedSimulator(weights, seed=3, change_interval=4)
    idx = [(slow.simulate(slices), slow.net_index)[1] for _ in range(8)]
    assert len(set(idx[:4])) == 1 and len(set(idx[4:])) == 1


@pytest.mark.parametrize("mode", ["first_batch", "none"])
def test_histogram_modes_and_options(weights, slices, mode):
    sim = LearnedSimulator(weights[0], histogram=mode, degrade=2.0, output_scale=0.5)
    img = sim.simulate(slices)
    assert img.shape == (5, 2, 40, 30) and float(img.max()) <= 0.5 + 1e-6
    with pytest.raises(ValueError):
        LearnedSimulator(weights[0], histogram="bogus")
    with pytest.raises(ValueError):
        LearnedSimulator([])
