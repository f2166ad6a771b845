"""The learned simulator's fast path (``FastGenerator``) against its reference (the ``UNet``
modules in float32), batch independence, and the per-env net carried by the slices."""

from dataclasses import replace

import pytest
import torch

from sonogym.learned_training.model_card import bone_surface_f1
from sonogym.ultrasound import ModelBasedSimulator, ProbeGeometry, Slicer
from sonogym.ultrasound.learned import UNet, UNetConfig
from sonogym.ultrasound.learned.inference import GROUP_NORM_MIN_PIXELS, FastGenerator
from sonogym.ultrasound.learned.shipped import NUM_SHIPPED, shipped_weights
from sonogym.ultrasound.learned.simulator import LearnedSimulator

torch.set_num_threads(1)
SHIPPED = [shipped_weights(k) for k in range(NUM_SHIPPED)]


def _random_unet(config: UNetConfig, seed: int) -> UNet:
    """A UNet with random weights, norm affines included (they start at 1 and 0)."""
    torch.manual_seed(seed)
    gen = UNet(config).eval()
    for m in gen.modules():
        if isinstance(m, torch.nn.InstanceNorm2d):
            torch.nn.init.uniform_(m.weight, 0.5, 1.5)
            torch.nn.init.normal_(m.bias, 0.0, 0.3)
    return gen


@pytest.mark.parametrize("config", [UNetConfig.from_width(8, 3), UNetConfig()], ids=str)
def test_fast_generator_matches_the_module(config):
    gen = _random_unet(config, 0)
    # 64 x 48: the top maps take the group-norm path, the lower ones the pooled one
    x = torch.rand(5, 1, 64, 48, generator=torch.Generator().manual_seed(1))
    assert 64 * 48 >= GROUP_NORM_MIN_PIXELS > 32 * 24
    with torch.no_grad():
        ref = gen(x)
    fast = FastGenerator(gen, "float32")(x)
    assert fast.dtype == torch.float32 and fast.shape == ref.shape
    assert (fast - ref).abs().max() < 2e-5
    half = FastGenerator(gen, "bfloat16")(x)
    assert half.dtype == torch.float32
    err = (half - ref).abs()
    assert err.mean() < 3e-3 and err.max() < 0.1
    assert not torch.equal(half, fast)  # bfloat16 is really used
    with pytest.raises(ValueError, match="divisible by"):
        FastGenerator(gen)(torch.rand(1, 1, 30, 48))
    with pytest.raises(ValueError, match="precision must be one of"):
        FastGenerator(gen, "float16")


@pytest.fixture(scope="module")
def env_slices(small_phantom):
    """12 navigation-like 2-D slices around L4, each env with its own shipped net."""
    c = small_phantom.landmarks.vertebra("L4").centre
    g = torch.Generator().manual_seed(0)
    u = torch.rand(12, 3, generator=g, dtype=torch.float64)
    x, z = c[0] + (u[:, 0] - 0.5) * 0.06, c[2] + (u[:, 1] - 0.5) * 0.06
    pos, rot = small_phantom.skin.surface_pose(x, z, 1.5 + 2.0 * u[:, 2])
    s = Slicer(small_phantom, ProbeGeometry.linear_2d())(pos.float(), rot.float())
    return replace(s, net_index=torch.tensor([0, 3, 1, 4, 2, 0, 0, 1, 4, 3, 2, 4]))


def _sim(small_phantom, **kw) -> LearnedSimulator:
    sim = LearnedSimulator(SHIPPED, **kw)
    sim.fit_source(small_phantom.ct)
    return sim


def test_fast_path_matches_the_reference_on_the_shipped_nets(small_phantom, env_slices):
    ref = _sim(small_phantom, reference=True).simulate(env_slices)
    fast = _sim(small_phantom).simulate(env_slices)
    assert (fast - ref).abs().max() < 1e-5  # measured 2e-6: summation order only
    half = _sim(small_phantom, precision="bfloat16").simulate(env_slices)
    err = (half - ref).abs()
    assert err.mean() < 2e-3 and err.max() < 0.1
    f1 = [bone_surface_f1(im, env_slices.labels)["f1"] for im in (ref, half)]
    assert f1[1] == pytest.approx(f1[0], abs=0.02)
    with pytest.raises(ValueError, match="reference=True runs the float32 modules"):
        LearnedSimulator(SHIPPED[0], reference=True, precision="bfloat16")


@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("precision", ["float32", "bfloat16"])
def test_an_env_image_does_not_depend_on_the_batch(small_phantom, env_slices, precision, threads):
    """An env alone, in a few envs or among all (other chunk sizes and compositions) gets the
    same image: bit for bit in bfloat16; in float32 within oneDNN's summation order (its
    convolutions pick kernels by batch size, as the module's do)."""
    sim = _sim(small_phantom, precision=precision, batch_size=3)
    torch.set_num_threads(threads)
    try:
        full = sim.simulate(env_slices)
        for idx in ([5], [2, 7, 11], [0, 1, 2, 3, 4, 5, 6]):
            part = sim.simulate(env_slices.select(torch.tensor(idx)))
            if precision == "bfloat16":
                assert torch.equal(part, full[idx]), idx
            else:
                assert (part - full[idx]).abs().max() < 1e-5, idx
    finally:
        torch.set_num_threads(1)


def test_each_env_is_imaged_by_the_net_its_slices_name(small_phantom, env_slices):
    sim = _sim(small_phantom)
    images = sim.simulate(env_slices)
    for k in range(NUM_SHIPPED):
        alone = sim.simulate(replace(env_slices, net_index=torch.full((12,), k)))
        rows = env_slices.net_index == k
        assert torch.equal(images[rows], alone[rows])
    # without net_index one net images the whole batch
    one = sim.simulate(replace(env_slices, net_index=None))
    assert any(torch.equal(one, sim.simulate(replace(env_slices, net_index=torch.full((12,), k))))
               for k in range(NUM_SHIPPED))  # fmt: skip
    with pytest.raises(ValueError, match=r"net indices must be in \[0, 5\)"):
        sim.simulate(replace(env_slices, net_index=torch.full((12,), 5)))
    with pytest.raises(ValueError, match=r"net indices must be in \[0, 5\)"):
        sim.simulate(replace(env_slices, net_index=torch.full((12,), -1)))
    with pytest.raises(ValueError, match="net_index has 3 entries for 12 slices"):
        sim.simulate(replace(env_slices, net_index=torch.zeros(3, dtype=torch.long)))


def test_net_index_travels_with_the_slices_and_model_based_ignores_it(env_slices):
    part = env_slices.select(torch.tensor([1, 3]))
    assert part.net_index.tolist() == [3, 4]
    both = type(env_slices).cat([part, env_slices.select(slice(0, 1))])
    assert both.net_index.tolist() == [3, 4, 0]
    with pytest.raises(ValueError, match="net_index"):
        type(env_slices).cat([part, replace(part, net_index=None)])
    mb = ModelBasedSimulator("reference")
    assert torch.equal(mb.simulate(part), mb.simulate(replace(part, net_index=None)))
