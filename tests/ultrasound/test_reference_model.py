"""The ``reference`` model against the reference's model (the authors' reference code),
recomputed here by hand with numpy on tiny inputs, term by term."""

import dataclasses
import math

import numpy as np
import pytest
import torch
from scipy import signal
from us_synthetic import BONE, MUSCLE, SOFT, block_patient, layered_patient, straight_down

from sonogym.ultrasound import (
    REFERENCE_LABEL_TISSUE,
    REFERENCE_TISSUES,
    ModelBasedSimulator,
    ProbeGeometry,
    ReferenceModel,
    Slicer,
    Slices,
    TissueTable,
)

# Deterministic scatterers (density 1, no amplitude noise): S = mu0 exactly.
DENSE = TissueTable(
    REFERENCE_LABEL_TISSUE,
    {k: dataclasses.replace(t, mu1=50.0, sigma0=0.0) for k, t in REFERENCE_TISSUES.items()},
    12,
)
PLAIN = ReferenceModel(tissues=DENSE, large_scale_amplitude=0.0, gel_depth=0.0)


def _slices(ct: np.ndarray, lab: np.ndarray, spacing: float = 0.5e-3) -> Slices:
    """Hand-made slices of one env (H, W), any geometry."""
    h, w = ct.shape
    probe = ProbeGeometry(h, w, 1, spacing, spacing, spacing)
    return Slices(
        torch.tensor(ct, dtype=torch.float32)[None, None],
        torch.tensor(lab, dtype=torch.uint8)[None, None],
        torch.zeros(1, 1, 3, dtype=torch.float64),
        torch.tensor([[0.0, spacing, 0.0]], dtype=torch.float64),
        torch.tensor([[spacing, 0.0, 0.0]], dtype=torch.float64),
        torch.tensor([1]),
        torch.tensor([0]),
        probe,
    )


def _psf(sa, sl):
    i = np.arange(-5, 6)
    return np.exp(-(i[:, None] ** 2) / (2 * sa**2)) * np.exp(-(i[None, :] ** 2) / (2 * sl**2))


def reference(ct, lab):
    """§1.7-§1.8 literally, per 0.5 mm pixel, for deterministic scatterers."""
    tissue = np.vectorize(lambda v: REFERENCE_LABEL_TISSUE[int(v)])(lab)
    alpha = np.vectorize(lambda t: REFERENCE_TISSUES[t].alpha)(tissue)
    mu0 = np.vectorize(lambda t: REFERENCE_TISSUES[t].mu0)(tissue)
    c = (np.clip(ct, -300, 3000) + 300) / 3300 * 255  # §1.7
    z = 100 * c  # CT mode
    zu = np.concatenate([z[1:2], z[:-1]])  # reflect padding at the top
    rho = ((zu - z) / (zu + z + 1e-5)) ** 2
    a_b = np.exp(-20 * 0.0005 * np.cumsum(alpha - 0.2, 0))  # f e = 20 * 0.0005
    a_r = np.exp(-20 * 0.0005 * np.cumsum(alpha - 0.0, 0))
    r0 = np.minimum(1.0 * a_r * rho, 0.1)
    r = signal.correlate2d(r0, _psf(3, 3), mode="same")  # zero padding
    b = 1.0 * a_b * signal.correlate2d(mu0, _psf(1, 2), mode="same")
    return 20 * r + b, dict(rho=rho, a_b=a_b, a_r=a_r, r0=r0, r=r, b=b)


def _tiny():
    h, w = 14, 9
    ct = np.full((h, w), 40.0)
    lab = np.full((h, w), SOFT)
    ct[5:9], lab[5:9] = 1400.0, BONE
    ct[9:, 4:], lab[9:, 4:] = 50.0, MUSCLE
    ct += np.random.default_rng(0).normal(0, 20, ct.shape)
    return ct, lab


def test_psf_kernels_are_the_references():
    k = ModelBasedSimulator(PLAIN)._constants(ProbeGeometry.linear_2d())
    (ra, rl), (ba, bl) = k["psf_r"], k["psf_b"]
    assert sum(ra) * sum(rl) == pytest.approx(49.4, abs=0.05)  # §1.8 step 10
    assert sum(ba) * sum(bl) == pytest.approx(12.5, abs=0.05)
    np.testing.assert_allclose(ra, np.exp(-(np.arange(-5, 6) ** 2) / 18), rtol=1e-12)
    np.testing.assert_allclose(bl, np.exp(-(np.arange(-5, 6) ** 2) / 8), rtol=1e-12)


def test_whole_model_matches_the_reference_on_a_tiny_input():
    ct, lab = _tiny()
    raw = ModelBasedSimulator(PLAIN).simulate_raw(_slices(ct, lab))[0, 0].double().numpy()
    ref, _ = reference(ct, lab)
    np.testing.assert_allclose(raw, ref, rtol=2e-4, atol=1e-5)


def test_each_term_by_hand():
    """One term at a time: switch the others off through the model's constants."""
    ct, lab = _tiny()
    _, terms = reference(ct, lab)
    s = _slices(ct, lab)
    # backscatter only (no reflection): E_S = 0
    b = ModelBasedSimulator(dataclasses.replace(PLAIN, e_s_ratio=0.0)).simulate_raw(s)
    np.testing.assert_allclose(b[0, 0].numpy(), terms["b"], rtol=2e-4, atol=1e-6)
    # reflection only: all mu0 = 0
    dark = TissueTable(
        REFERENCE_LABEL_TISSUE,
        {k: dataclasses.replace(t, mu0=0.0, sigma0=0.0) for k, t in REFERENCE_TISSUES.items()},
        12,
    )
    r = ModelBasedSimulator(dataclasses.replace(PLAIN, tissues=dark)).simulate_raw(s)
    np.testing.assert_allclose(r[0, 0].numpy(), 20 * terms["r"], rtol=2e-4, atol=1e-6)
    # the clip at 0.1 is active at the bone's top edge and nowhere in soft tissue
    assert terms["r0"][5].max() == 0.1 and terms["rho"][5].min() > 0.1
    assert terms["r0"][1:4].max() < 0.05  # CT texture reflects weakly


def test_attenuation_by_hand():
    """Uniform muscle: B(y) = mu0 * (PSF_B sum) * exp(-0.01 * (1.09 - 0.2) * (y + 1))."""
    h, w = 60, 31
    ct, lab = np.full((h, w), 50.0), np.full((h, w), MUSCLE)
    raw = ModelBasedSimulator(PLAIN).simulate_raw(_slices(ct, lab))[0, 0].double().numpy()
    y = np.arange(h)
    psf_sum = _psf(1, 2).sum()
    expected = 0.7 * psf_sum * np.exp(-0.01 * 0.89 * (y + 1))
    np.testing.assert_allclose(raw[6:-6, w // 2], expected[6:-6], rtol=1e-4)


def test_observation_is_scaled_and_clipped():
    ct, lab = _tiny()
    s = _slices(ct, lab)
    sim = ModelBasedSimulator(PLAIN)
    raw, obs = sim.simulate_raw(s), sim.simulate(s)
    torch.testing.assert_close(obs, (0.02 * raw).clamp(0, 1))
    hot = ModelBasedSimulator(dataclasses.replace(PLAIN, observation_scale=1.0)).simulate(s)
    assert hot.max() == 1.0


def test_scatterer_statistics():
    """Random scatterers: a fraction Phi(mu1) of pixels scatters, with amplitude mu0 + s0 N."""
    h, w = 200, 150
    model = ReferenceModel(large_scale_amplitude=0.0, gel_depth=0.0)
    sim = ModelBasedSimulator(model)
    k = sim._constants(ProbeGeometry.linear_2d())
    for label, tissue in ((SOFT, 12), (BONE, 13)):
        lab12 = torch.full((4, h, w), label << 12, dtype=torch.int32)  # labels << 12
        o = torch.rand(4, 3, dtype=torch.float64) * 0.01
        rows = torch.tensor([[0.0, 0.5e-3, 0.0]] * 4, dtype=torch.float64)
        cols = torch.tensor([[0.5e-3, 0.0, 0.0]] * 4, dtype=torch.float64)
        mix = torch.tensor([1, 2, 3, 4])
        amp, _ = sim._scatterers(lab12, (o, rows, cols, mix, mix), k, sim._chunks.workspaces[0])
        t = REFERENCE_TISSUES[tissue]
        density = 0.5 * (1 + math.erf(t.mu1 / math.sqrt(2)))
        on = amp[amp > 0]
        assert (amp > 0).float().mean() == pytest.approx(density, abs=0.01)
        assert on.mean() == pytest.approx(t.mu0, abs=0.005)
        assert on.std() == pytest.approx(t.sigma0, abs=0.01)


def test_large_scale_modulation_is_per_env_and_patient_fixed():
    p = layered_patient([(0.12, SOFT)], size_xz=(0.3, 0.3))
    sl = Slicer(p)
    model = ReferenceModel(large_scale_amplitude=0.5)  # exaggerated to see it
    sim = ModelBasedSimulator(model)
    pos, rot = straight_down(3, x=torch.tensor([-0.08, 0.08, -0.08]), z=0.0)
    raw = sim.simulate_raw(sl(pos, rot))[:, 0]
    # the coarse field: mean brightness per 15 mm cell differs between envs 0 and 1 ...
    cells = raw[:, 10:190, 10:140].unfold(1, 30, 30).unfold(2, 30, 30).mean((-1, -2))
    assert (cells[0] - cells[1]).abs().mean() > 0.1 * cells.mean()
    # ... and is the same where the patient is the same (envs 0 and 2)
    torch.testing.assert_close(raw[0], raw[2])


def test_magnitude_matches_the_reference_on_a_block_phantom():
    """The authors' reference code: bone peak 15-21, soft-tissue mean 2.6-3.4 (raw)."""
    p = block_patient(soft_depth=0.01, muscle_depth=0.015, ct_noise=10.0)
    sl = Slicer(p)
    pos, rot = straight_down(
        8, x=torch.linspace(-0.005, 0.005, 8), z=torch.linspace(-0.02, 0.02, 8)
    )
    raw = ModelBasedSimulator("reference").simulate_raw(sl(pos, rot))[:, 0]
    bone_rows = raw[:, 40:60, 60:90]  # bone surface at 25 mm = row 50
    peak = bone_rows.amax((1, 2))
    assert torch.all((peak > 15) & (peak < 21)), peak
    soft = raw[:, 8:18, :].mean()  # soft tissue between the gel band and the muscle (10 mm)
    assert 2.6 < soft < 3.4, soft


def test_air_gap_blocks_the_beam():
    p = layered_patient([(0.05, SOFT), (0.02, BONE), (0.03, SOFT)], air_above=0.03)
    sl = Slicer(p)
    sim = ModelBasedSimulator("reference")
    on = sim.simulate_raw(sl(*straight_down(1)))
    off = sim.simulate_raw(sl(*straight_down(1, y=-0.01)))  # 10 mm air gap
    assert on[0, 0, 30:].mean() > 1.0
    assert off[0, 0, 21:].abs().max() < 1e-6  # nothing below the gap (rows >= 10 mm)


@pytest.mark.parametrize("model", ["reference", "physical"])
def test_coarser_probe_images_tissue_the_same_way(model):
    """Physical units: a 2 mm probe sees soft tissue and a bone line like the 0.5 mm one."""
    p = layered_patient([(0.025, SOFT), (0.01, BONE), (0.03, SOFT)], size_xz=(0.2, 0.2))
    sl_fine = Slicer(p)
    coarse = ProbeGeometry(50, 37, 1, 2e-3, 2e-3, 2e-3)
    sl_coarse = Slicer(p, coarse)
    pos, rot = straight_down(
        10, x=torch.linspace(-0.03, 0.03, 10), z=torch.linspace(-0.03, 0.03, 10)
    )
    sim = ModelBasedSimulator(model)
    fine = sim.simulate_raw(sl_fine(pos, rot))[:, 0]
    crs = sim.simulate_raw(sl_coarse(pos, rot))[:, 0]
    soft_f = fine[:, 14:44, 20:130].mean()  # 7-22 mm
    soft_c = crs[:, 4:11, 5:32].mean()  # 8-22 mm
    assert float(soft_c) == pytest.approx(float(soft_f), rel=0.15)
    line_f = fine[:, 44:56].amax(1).mean()  # bone surface at 25 mm
    line_c = crs[:, 11:14].amax(1).mean()
    assert float(line_c) == pytest.approx(float(line_f), rel=0.35)
