"""What an env will take before it is built: memory from its env and patient counts, disk
for the phantoms the cache does not hold yet; refused up front when it does not fit.

Memory (``env_memory``): ``BASE + per_env N + (PATIENT_FIXED + (per_patient - PATIENT_FIXED)
s) P + load_peak s`` bytes, with ``s = (1 mm / spacing)^3``, ``N`` envs, ``P`` distinct patients and
the task's ``EnvMemory`` constants. They were measured as the memory growth of a fresh process
(one torch thread) that imports sonogym, builds the env with default options at 1 mm and takes
three expert steps (``benchmarks/footprint.py``):

=============== ====================== ======================= ==========================
task            per env (1 -> 64 envs)  per patient (1 -> 3)     load peak (high-water mark)
=============== ====================== ======================= ==========================
navigation      0.88 MB (1 -> 256)      46 MB                    166 MB
reconstruction  2.24 MB                 202 MB                   269 MB
surgery         0.81 MB                 196 MB                   23 MB
=============== ====================== ======================= ==========================

Per patient is the growth of the process's high-water mark from 1 to 3 patients (4 envs,
phantom generator 10, phantoms in the cache); the load peak is what is left of the
high-water mark of one patient after ``BASE``, its envs and the patient. Navigation crops
each patient as it loads and keeps no full volume, so its patients cost their slicer crop
(its resident memory grows by 38 MB per patient); reconstruction and surgery hold every
patient whole before cropping (resident growth 84 and 39 MB per patient). ``BASE`` is what
is left of one env on one patient (25-60 MB); ``PATIENT_FIXED`` the part of a patient that
does not scale with its voxels (surface maps, landmarks). Real TotalSegmentator folders are
counted as phantoms at the same spacing (their loader checks its own peak). Other options
move the figure: ``obs_mode="state"`` renders no images (less), navigation's
``"us_memory"`` keeps ``memory_lag`` + 1 images per env (0.93 MB more per env at the
default 30; ``"us_scan"`` one image more), ``crop_to_reach=False`` keeps whole volumes
(more), the learned simulator adds its networks.

Disk: each phantom seed not yet in the cache adds ``anatomy.phantom.cache_entry_bytes`` (90 MB
at 1 mm; 65-84 MB measured, 17-21 s to build each) under ``$SONOGYM_CACHE``.

Both limits are ``sonogym.memory.check_fits``'s: 80 % of the memory free on the env's device,
80 % of the free disk of the cache's file system.
"""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

from sonogym.envs.spec import EnvMemory
from sonogym.memory import USABLE_FRACTION, check_fits, free_memory

#: Bytes of an env's process beyond its envs and patients (robot models, tables, buffers).
BASE = 60e6
#: Bytes of each patient that do not scale with its voxel count (surface maps, landmarks).
PATIENT_FIXED = 6e6


def env_memory(memory: EnvMemory, num_envs: int, num_patients: int, spacing: float) -> float:
    """Estimated resident bytes of an env (see the module doc)."""
    scale = (1e-3 / spacing) ** 3
    patients = num_patients * (PATIENT_FIXED + (memory.per_patient - PATIENT_FIXED) * scale)
    return BASE + memory.per_env * num_envs + patients + memory.load_peak * scale


def config_memory(memory: EnvMemory, num_envs: int, cfg: Any) -> float:
    """``env_memory`` of ``num_envs`` envs of a task config (its ``patients``, counted once
    each, and ``phantom_spacing``)."""
    patients = len(set(map(str, cfg.patients)))
    return env_memory(memory, num_envs, patients, float(cfg.phantom_spacing))


def check_env_fits(task: str, memory: EnvMemory, num_envs: int, cfg: Any) -> None:
    """Refuse an env of ``num_envs`` envs over ``cfg.patients`` at ``cfg.phantom_spacing`` whose
    memory (on ``cfg.device``) or phantom cache (on disk) would not fit, before anything is
    loaded or built: ``ResourceLimitError`` with the estimate, the limit and what to lower."""
    patients, spacing = len(set(map(str, cfg.patients))), float(cfg.phantom_spacing)
    if not spacing > 0:
        raise ValueError(f"phantom_spacing must be > 0 (metres, 1 mm = 0.001), got {spacing}")
    check_fits(
        config_memory(memory, num_envs, cfg), free_memory(cfg.device), f"a {task} env of "
        f"{num_envs} envs over {patients} patients at {spacing * 1e3:g} mm", "memory",
        "use fewer envs (num_envs, --envs) or patients, or a coarser phantom_spacing",
    )  # fmt: skip
    seeds = sorted({p for p in cfg.patients if isinstance(p, int) and not isinstance(p, bool)})
    if seeds:
        check_phantom_cache(seeds, spacing)


def check_phantom_cache(seeds: list[int], spacing: float) -> None:
    """Refuse building phantoms ``seeds`` at ``spacing`` when the ones the cache lacks would
    not fit its disk."""
    from sonogym.anatomy.phantom import PhantomParams, cache_dir, cache_entry_bytes, is_cached

    folder = cache_dir()
    free = _free_disk(folder)
    per = cache_entry_bytes(spacing)
    if free is None or len(seeds) * per <= USABLE_FRACTION * free:  # fits if none is cached
        return
    try:
        params = PhantomParams(spacing=spacing)
    except ValueError:  # the phantom refuses this spacing, naming it, when it is built
        return
    missing = sum(not is_cached(s, params) for s in seeds)
    check_fits(
        missing * per, free, f"building {missing} phantoms the cache lacks ({per / 1e6:.0f} MB "
        f"and ~20 s each at {spacing * 1e3:g} mm)", f"disk under {folder}",
        "use fewer phantom seeds, free disk space, or point SONOGYM_CACHE at a larger disk",
    )  # fmt: skip


def _free_disk(folder: Path) -> int | None:
    """Free bytes of the file system ``folder`` is (or will be) on."""
    for p in (folder, *folder.parents):
        if p.exists():
            return shutil.disk_usage(p).free
    return None
