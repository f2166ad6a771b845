"""Properties both ultrasound models share: determinism, patient-fixed speckle, batching, errors."""

import pytest
import torch
from us_synthetic import block_patient, random_poses, straight_down

from sonogym.ultrasound import (
    ModelBasedSimulator,
    PhysicalModel,
    ProbeGeometry,
    Slicer,
    UltrasoundSimulator,
    make_model,
)

MODELS = ["physical", "reference"]


@pytest.fixture(scope="module")
def patient():
    return block_patient(ct_noise=10.0)


@pytest.fixture(scope="module")
def slicer(patient):
    return Slicer(patient)


def _corr(a, b):
    return torch.corrcoef(torch.stack([a.flatten(), b.flatten()]))[0, 1].item()


@pytest.mark.parametrize("model", MODELS)
def test_same_pose_gives_the_same_image(slicer, model):
    pos, rot = random_poses(3, seed=1)
    sim = ModelBasedSimulator(model)
    a = sim.simulate(slicer(pos, rot))
    b = ModelBasedSimulator(model).simulate(slicer(pos, rot))
    assert torch.equal(a, b)
    assert a.shape == (3, 1, 200, 150) and a.dtype == torch.float32
    assert a.min() >= 0 and a.max() <= 1


@pytest.mark.parametrize("model", MODELS)
def test_shifted_pose_gives_a_correlated_image(slicer, model):
    pos, rot = straight_down(1, z=0.01)
    sim = ModelBasedSimulator(model)
    a = sim.simulate_raw(slicer(pos, rot))[0, 0]
    shifted = pos.clone()
    shifted[:, 0] += 0.5e-3  # half a millimetre = one pixel along the array
    b = sim.simulate_raw(slicer(shifted, rot))[0, 0]
    assert _corr(a[:, 1:], b[:, :-1]) > 0.95  # the same speckle, moved with the anatomy
    assert _corr(a, b) > 0.5  # strongly correlated even without re-aligning
    elevation = pos.clone()
    elevation[:, 2] += 0.5e-3  # out of plane, one noise cell: the anatomy stays, the speckle is
    c = sim.simulate_raw(slicer(elevation, rot))[0, 0]  # redrawn (no elevation PSF, as the ref.)
    pool = torch.nn.functional.avg_pool2d
    assert _corr(pool(a[None], 10), pool(c[None], 10)) > 0.9
    far = pos.clone()
    far[:, 2] += 0.02  # 2 cm away: independent speckle
    d = sim.simulate_raw(slicer(far, rot))[0, 0]

    # speckle alone: soft tissue away from the gel band, the muscle and the image edges, with
    # each row's mean removed (the depth profile is the same in every image)
    def speckle(x):
        x = x[10:36, 12:138]
        return x - x.mean(1, keepdim=True)

    assert abs(_corr(speckle(a), speckle(d))) < 0.25  # independent (~300 speckle cells)
    assert _corr(speckle(a[:, 1:]), speckle(b[:, :-1])) > 0.95


@pytest.mark.parametrize("model", MODELS)
def test_batched_equals_one_by_one(slicer, model):
    pos, rot = random_poses(5, seed=2)
    sim = ModelBasedSimulator(model, chunk_pixels=2 * 200 * 150)  # chunks of two images
    batch = sim.simulate(slicer(pos, rot))
    for i in range(5):
        one = ModelBasedSimulator(model).simulate(slicer(pos[i : i + 1], rot[i : i + 1]))
        assert torch.equal(one[0], batch[i])


@pytest.mark.parametrize("model", MODELS)
def test_volume_probe(patient, model):
    probe = ProbeGeometry.volume_3d()
    pos, rot = random_poses(2, seed=3, max_angle=0.2)
    img = ModelBasedSimulator(model).simulate(Slicer(patient, probe)(pos, rot))
    assert img.shape == (2, 5, 50, 37)
    assert img.min() >= 0 and img.max() <= 1 and img.std() > 0.01


@pytest.mark.parametrize("model", MODELS)
def test_out_buffer(slicer, model):
    pos, rot = random_poses(2, seed=4)
    s = slicer(pos, rot)
    sim = ModelBasedSimulator(model)
    out = torch.empty(2, 1, 200, 150)
    res = sim.simulate(s, out=out)
    assert res.data_ptr() == out.data_ptr() and torch.equal(res, sim.simulate(s))
    with pytest.raises(ValueError, match="out must be"):
        sim.simulate(s, out=torch.empty(3, 1, 200, 150))


def test_unknown_model_lists_the_known_ones():
    with pytest.raises(ValueError, match=r"unknown ultrasound model 'fancy'.*physical.*reference"):
        ModelBasedSimulator("fancy")


def test_bad_input_raises(slicer):
    sim = ModelBasedSimulator("physical")
    with pytest.raises(TypeError, match="Slices"):
        sim.simulate(torch.zeros(1, 1, 200, 150))


def test_protocol_and_models():
    sim = ModelBasedSimulator("reference")
    assert isinstance(sim, UltrasoundSimulator)
    assert sim.model.name == "reference" and make_model("physical").name == "physical"
    model = PhysicalModel(frequency=5e6)
    assert ModelBasedSimulator(model).model is model
    assert model.axial_sigma < PhysicalModel().axial_sigma  # shorter wavelength, finer PSF


def test_the_former_model_name_warns_and_gives_the_reference_model(slicer):
    """The reference model's former name, "sonogym", works until 0.3.0 removes it."""
    from sonogym.ultrasound import ReferenceModel

    with pytest.warns(DeprecationWarning, match="'sonogym' is now called 'reference'.*0.3.0"):
        old = ModelBasedSimulator("sonogym")
    assert isinstance(old.model, ReferenceModel) and old.model.name == "reference"
    s = slicer(*random_poses(2, seed=3))
    assert torch.equal(old.simulate(s), ModelBasedSimulator("reference").simulate(s))


def test_the_former_preset_spellings_are_refused():
    """The models were called presets before "preset" meant the device preset only."""
    import sonogym.ultrasound as us

    with pytest.raises(TypeError, match="preset"):
        ModelBasedSimulator(preset="physical")
    with pytest.raises(TypeError, match="preset"):
        make_model(preset="physical")
    assert not hasattr(ModelBasedSimulator("physical"), "preset")
    for module in (us, us.simulator):
        with pytest.raises(AttributeError, match="PRESETS"):
            module.PRESETS  # noqa: B018


def test_memory_is_small(slicer):
    """Nothing dense per patient: tables and scratch only (<= 300 MB/patient)."""
    sim = ModelBasedSimulator("physical")
    sim.simulate(slicer(*random_poses(4, seed=5)))
    assert sim.nbytes < 40e6
    assert slicer.nbytes < 3.5 * slicer.num_voxels + 40e6


@pytest.mark.parametrize("taps", [[1.0], [1.0] * 3, [1.0] * 5, [0.2, 1.0, 0.3], [0.0, 1.0, 0.5]])
@pytest.mark.parametrize("h", [1, 2, 7])
def test_blur_with_a_unit_centre_tap_matches_the_multiply_first_blur(taps, h):
    # blur_1d skips the multiply when the centre tap is 1 (the physical model's 1 mm interface
    # sum and its axial PSF): bit for bit the multiply-then-add correlation, zero beyond edges
    from sonogym.ultrasound import psf

    x = torch.randn(3, h, 4, generator=torch.Generator().manual_seed(h + len(taps)))
    got = psf.blur_1d(x, taps, -2, out=torch.empty_like(x))
    r = (len(taps) - 1) // 2
    ref = x * taps[r]
    for k in range(1, min(r, h - 1) + 1):
        if taps[r - k]:
            ref[:, k:].add_(x[:, : h - k], alpha=taps[r - k])
        if taps[r + k]:
            ref[:, : h - k].add_(x[:, k:], alpha=taps[r + k])
    assert torch.equal(got, ref)
    assert torch.equal(psf.blur_1d(x, taps, -2), ref)  # without out=
    for y in range(h):
        want = sum(taps[r + d] * x[:, y + d] for d in range(-r, r + 1) if 0 <= y + d < h)
        assert torch.allclose(got[:, y], want, atol=1e-6)
