"""A built env keeps no full patient volume: the slicer's compact copy (float16 CT, uint8
labels) is what images come from; the scene keeps each patient's grid, skin and landmarks."""

from __future__ import annotations

import math

import pytest
import torch

from sonogym.anatomy import Patient, PatientModel
from sonogym.envs.patients import resolve_patients
from sonogym.envs.registry import make_vec


def _tensors(root) -> list[torch.Tensor]:
    """Every tensor reachable from ``root`` through sonogym objects, dicts, lists, tuples."""
    seen, out, stack = set(), [], [root]
    while stack:
        o = stack.pop()
        if id(o) in seen:
            continue
        seen.add(id(o))
        if isinstance(o, torch.Tensor):
            out.append(o)
        elif isinstance(o, dict):
            stack.extend(o.values())
        elif isinstance(o, list | tuple):
            stack.extend(o)
        elif type(o).__module__.startswith("sonogym") and hasattr(o, "__dict__"):
            stack.extend(vars(o).values())
    return out


@pytest.mark.parametrize("task", ["navigation", "reconstruction", "surgery"])
def test_built_env_keeps_no_full_patient_volume(task):
    torch.set_num_threads(1)
    env = make_vec(task, 2, phantom_spacing=0.002)
    (full,) = resolve_patients(0, 0.002)
    assert isinstance(full, Patient)
    voxels = math.prod(full.shape)
    pats = env.scene.patients
    assert all(isinstance(p, PatientModel) for p in pats)
    assert pats[0].shape == full.shape and pats[0].name == full.name
    assert pats[0].landmarks.vertebra("L4").centre == pytest.approx(
        full.landmarks.vertebra("L4").centre
    )
    with pytest.raises(AttributeError, match="resolve_patients"):
        _ = pats[0].ct
    held = _tensors(env)
    # neither the patient's own CT / labels nor any same-sized float32 or uint8 volume
    assert not any(t.untyped_storage().data_ptr() == full.ct.data_ptr() for t in held)
    assert not any(t.untyped_storage().data_ptr() == full.labels.data_ptr() for t in held)
    assert not any(t.numel() == voxels and t.dtype == torch.float32 for t in held)
    # ... and images still come: the slicer holds the compact copy
    obs, _ = env.reset(seed=0)
    env.step(torch.zeros(env.action_space.shape))


@pytest.mark.parametrize("task", ["navigation", "reconstruction", "surgery"])
def test_envs_slice_only_what_their_probe_can_reach_with_the_same_images(task):
    """crop_to_reach (default) keeps a fraction of each volume; over random steps the slices
    equal the uncropped ones (CT to float32 rounding of coordinates, labels exactly)."""
    out = []
    for crop in (True, False):
        env = make_vec(task, 2, patients=(0,), phantom_spacing=0.002, crop_to_reach=crop)
        env.reset(seed=3)
        g = torch.Generator().manual_seed(0)
        high = torch.as_tensor(env.single_action_space.high)
        cts, labs = [], []
        for _ in range(12):
            env.step((torch.rand((2, *high.shape), generator=g) * 2 - 1) * high)
            s = env.scene.slices()
            cts.append(s.ct.clone())
            labs.append(s.labels.clone())
        out.append((torch.stack(cts), torch.stack(labs), env.scene.slicer))
    (ct1, lab1, sl1), (ct0, lab0, sl0) = out
    assert sl1.cropped and not sl0.cropped
    assert sl1.nbytes < 0.85 * sl0.nbytes
    assert (ct1 - ct0).abs().max() < 0.05 and torch.equal(lab1, lab0)


def test_navigation_loads_its_patients_one_at_a_time_into_the_same_slicer(monkeypatch):
    """Navigation reads volumes only through its slicer, so its scene crops each patient right
    after loading it (never all full volumes at once) and images the same as a scene that loads
    them all first."""
    import sonogym.envs.scene as scene_mod
    from sonogym.envs.probe_scene import ProbeScene
    from sonogym.ultrasound.slicer import PatientCrop

    events = []
    load, crop = scene_mod.resolve_patients, PatientCrop.of
    monkeypatch.setattr(
        scene_mod, "resolve_patients", lambda s, sp: events.append(("load", list(s))) or load(s, sp)
    )
    monkeypatch.setattr(
        PatientCrop,
        "of",
        staticmethod(lambda p, *a: events.append(("crop", p.name)) or crop(p, *a)),
    )
    env = make_vec("navigation", 4, patients=(0, 1), phantom_spacing=0.002, obs_mode="ct")
    assert events == [
        ("load", [0]), ("crop", "phantom-0"), ("load", [1]), ("crop", "phantom-1"),
    ]  # fmt: skip
    scene = env.scene
    assert isinstance(scene, ProbeScene) and scene.slicer.cropped
    whole_first = ProbeScene(env.cfg, 4, env.device, render=True, keep_volumes=True, aimed=True)
    assert whole_first.slicer.nbytes == scene.slicer.nbytes
    for k in ("_ct", "_nibbles", "_palette", "_offsets", "_lim"):
        assert torch.equal(getattr(whole_first.slicer, k), getattr(scene.slicer, k)), k
    env.reset(seed=2)
    whole_first.probe_pos, whole_first.probe_rot = scene.probe_pos, scene.probe_rot
    assert torch.equal(whole_first.observe("ct"), scene.observe("ct"))


_RESIDENT = """
import gc, json, sys, torch
torch.set_num_threads(1)
from pathlib import Path
from sonogym.envs.registry import make_vec
from sonogym.memory import return_freed_memory
env = make_vec("navigation", 6, patients=tuple(range(int(sys.argv[1]))), phantom_spacing=0.002)
env.reset(seed=0)
env.step(torch.zeros(env.action_space.shape))
gc.collect()
return_freed_memory()
rss = int(Path("/proc/self/statm").read_text().split()[1]) * 4096  # resident pages
print(json.dumps({"rss": rss, "slicer": env.scene.slicer.nbytes}))
"""


def test_resident_memory_per_extra_patient_is_the_slicers_copy():
    """What a user reads in ``top``: an env over 3 phantoms against one over 1, each in a fresh
    process (so nothing else in the process moves the figure), grows by the slicer's compact
    copy per extra patient and little more: no full volume stays loaded anywhere (a cache of
    whole patients held 4 of them: +10 MB per extra patient at 2 mm, +3x at 1 mm)."""
    import json
    import os
    import subprocess
    import sys

    from sonogym.envs.patients import resolve_patients

    for seed in range(3):  # into the phantom cache first: both processes only load
        resolve_patients(seed, 0.002)

    def run(patients: int) -> dict:
        env = {**os.environ, "OMP_NUM_THREADS": "1"}
        out = subprocess.run(
            [sys.executable, "-c", _RESIDENT, str(patients)],
            capture_output=True, text=True, check=True, env=env,
        )  # fmt: skip
        return json.loads(out.stdout)

    one, three = run(1), run(3)
    per_patient = (three["rss"] - one["rss"]) / 2 / 2**20
    slicer = (three["slicer"] - one["slicer"]) / 2 / 2**20
    assert 4 < slicer < 6  # MB: a phantom's crop at 2 mm (float16 CT, 4-bit labels)
    # skin maps (~0.4 MB at 2 mm) and landmarks are the rest
    assert per_patient < slicer + 1.5, f"{per_patient:.1f} MB per extra patient"


_LOAD_PEAK = """
import json, torch
torch.set_num_threads(1)
from pathlib import Path
from sonogym.envs.patients import resolve_patients
from sonogym.ultrasound.slicer import PatientCrop

def status(key):
    line = next(x for x in Path("/proc/self/status").read_text().splitlines() if x.startswith(key))
    return int(line.split()[1]) * 1024

Path("/proc/self/clear_refs").write_text("5")  # the high-water mark starts again from here
before = status("VmRSS")
patient = resolve_patients(0, 0.002)[0]
crop = PatientCrop.of(patient, None)
print(json.dumps({"peak": status("VmHWM") - before, "volumes": patient.ct.numel() * 5}))
"""


def test_loading_and_cropping_a_patient_peaks_near_its_volumes():
    """Loading a cached phantom (its skin and landmarks computed) and cropping it for a slicer
    holds the float32 CT and uint8 labels (5 bytes per voxel), the crop (2.5), the cache's
    int16 CT while it converts, bounded scratch and a first load's one-time costs; no other
    volume-sized temporaries (``isfinite`` of the whole CT, ``np.isin`` of the whole label
    map, an unchunked label packing). Fresh process, 2 mm: 3.4-4.0x the volumes' bytes
    measured, 5.1-5.3x with those temporaries."""
    import json
    import os
    import subprocess
    import sys

    resolve_patients(0, 0.002)  # into the phantom cache first: the process only loads
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    out = subprocess.run(
        [sys.executable, "-c", _LOAD_PEAK], capture_output=True, text=True, check=True, env=env
    )
    m = json.loads(out.stdout)
    assert m["peak"] < 4.6 * m["volumes"], f"{m['peak'] / m['volumes']:.2f}x the volumes"
