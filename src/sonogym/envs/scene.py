"""What every task's scene shares: per-env patients and the imaging of a probe on them.

``PatientScene`` holds, for N envs, the patients (env i -> patient i % P), their stacked skin
surfaces, the target vertebra's centre, and the imaging chain of one probe geometry: a slicer
over all patients, the ultrasound simulator (model-based preset or learned nets, one net per
env redrawn at its resets) and ``observe``, which images each env's reached probe pose.
Subclasses (``ProbeScene`` for navigation and reconstruction, ``SurgeryScene``) add the arms
and keep ``probe_pos`` (N, 3) and ``probe_rot`` (N, 3, 3) up to date.
"""

from __future__ import annotations

from dataclasses import replace
from functools import cached_property

import numpy as np
import torch

from sonogym.anatomy import Patient, SkinSurface
from sonogym.envs.imaging import NetChoice, build_simulator, check_simulator, simulate_us
from sonogym.envs.patients import resolve_patients, return_freed_memory
from sonogym.ultrasound import ProbeGeometry, Slicer, make_model

#: CT window of the "ct" observation mode, HU -> [0, 1].
CT_WINDOW = (-1000.0, 2000.0)


class PatientScene:
    """Patients + imaging for N envs (see the module docstring).

    Args:
        patients: phantom seeds and/or TotalSegmentator folders.
        num_envs: N.
        spacing: voxel size (m) of phantoms / resampled folders.
        simulator: "physical" or "sonogym" (model-based presets) or "learned".
        learned_nets: nets of ``simulator="learned"`` (ints: shipped nets, str: weight files);
            each env uses ``nets.index`` into them, redrawn by ``draw_nets`` at its resets.
        target_vertebra: the vertebra whose body centroid anchors goals and arm placement.
        device: torch device of everything.
        probe: the imaging geometry.
        gel_depth: m, coupling gel under the probe face, overriding the model-based preset's
            (None keeps the preset's).
        learned_precision: working precision of the learned nets ("float32", "bfloat16").
    """

    def __init__(
        self,
        patients,
        num_envs: int,
        spacing: float,
        simulator: str,
        learned_nets,
        target_vertebra: str,
        device: torch.device,
        probe: ProbeGeometry,
        gel_depth: float | None = None,
        learned_precision: str = "float32",
    ) -> None:
        check_simulator(simulator, learned_nets, learned_precision)
        self.learned_precision = learned_precision
        self.device = device
        self.num_envs = num_envs
        self.simulator_name = simulator
        self.learned_nets = tuple(learned_nets)
        self.nets = NetChoice(num_envs, len(self.learned_nets), device)
        self.probe_geometry = probe
        self.gel_depth = gel_depth
        self.patients = resolve_patients(patients, spacing)
        self.patient_index = torch.arange(num_envs, device=device) % len(self.patients)
        self.skin = SkinSurface.stack([p.skin for p in self.patients]).to(device)
        centres = np.array([p.landmarks.vertebra(target_vertebra).centre for p in self.patients])
        #: (P, 3) float64 and (N, 3) float32: the target vertebra's body centroid in {P}, m.
        self.target_centres_p = torch.tensor(centres, dtype=torch.float64, device=device)
        self.target_centres = self.target_centres_p[self.patient_index].float()
        self.probe_pos = torch.zeros(num_envs, 3, device=device)
        self.probe_rot = torch.eye(3, device=device).repeat(num_envs, 1, 1)

    # ---------------------------------------------------------------- imaging
    @cached_property
    def slicer(self) -> Slicer:
        return Slicer(self.patients, self.probe_geometry, device=self.device)

    @cached_property
    def simulator(self):
        model = None
        if self.simulator_name != "learned" and self.gel_depth is not None:
            model = replace(make_model(self.simulator_name), gel_depth=float(self.gel_depth))
        return build_simulator(
            self.simulator_name, self.patients, self.device, self.learned_nets, model,
            self.learned_precision,
        )  # fmt: skip

    def build_imaging(self) -> None:
        """Build the slicer and the simulator now (else on the first ``observe``)."""
        _ = self.slicer, self.simulator

    def release_volumes(self) -> None:
        """Build the imaging, then keep only each patient's ``PatientModel`` (grid, skin,
        landmarks): the slicer holds its own compact copy of the volumes, so the full float32
        CT and labels (5 bytes per voxel) need not stay. Envs call this at the end of their
        construction, after everything that reads the volumes."""
        self.build_imaging()
        self.patients = [p.model() if isinstance(p, Patient) else p for p in self.patients]
        return_freed_memory()

    def draw_nets(self, env_ids: torch.Tensor, u: torch.Tensor) -> None:
        """Draw the learned net of each env in ``env_ids`` from uniforms ``u`` (see NetChoice)."""
        self.nets.draw(env_ids, u)

    @property
    def image_shape(self) -> tuple[int, ...]:
        """(E, H, W) of the probe's images."""
        return self.probe_geometry.shape

    def slices(self, env_ids: torch.Tensor | None = None):
        """CT and label slices at the reached probe poses of ``env_ids`` (None: all)."""
        sl = slice(None) if env_ids is None else env_ids
        return self.slicer(self.probe_pos[sl], self.probe_rot[sl], self.patient_index[sl])

    def observe(self, mode: str, env_ids: torch.Tensor | None = None) -> torch.Tensor:
        """Images of the reached probe poses (see ``image_observation``), (K, E, H, W)."""
        return image_observation(self.slices(env_ids), mode, self, env_ids)


def image_observation(slices, mode: str, scene: PatientScene, env_ids=None) -> torch.Tensor:
    """An image observation of sliced CT + labels: "us" the ultrasound simulated by
    ``scene.simulator`` (N, E, H, W) in [0, 1] (the simulator is built only for this mode; the
    learned one uses each env's net), "ct" the CT windowed from ``CT_WINDOW`` to [0, 1],
    "labels" the uint8 ids. ``env_ids``: the envs the slices belong to (None: all)."""
    if mode == "us":
        return simulate_us(scene, slices, env_ids).float()
    if mode == "ct":
        lo, hi = CT_WINDOW
        return ((slices.ct - lo) / (hi - lo)).clamp(0, 1)
    if mode == "labels":
        return slices.labels
    raise ValueError(f"unknown image mode {mode!r}")
