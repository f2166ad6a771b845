"""What every task's scene shares: per-env patients and the imaging of a probe on them.

``PatientScene`` holds, for N envs, the patients (env i -> patient i % P), their stacked skin
surfaces, the target vertebra's centre, and the imaging chain of one probe geometry: a slicer over
all patients, the ultrasound simulator (a model-based ultrasound model, or learned nets, one net per
env redrawn at its resets) and ``observe``, which images each env's reached probe pose. Subclasses
(``ProbeScene`` for navigation and reconstruction, ``SurgeryScene``) add the arms and keep
``probe_pos`` (N, 3) and ``probe_rot`` (N, 3, 3) up to date.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import cached_property
from pathlib import Path

import numpy as np
import torch

from sonogym.anatomy import Patient, SkinSurface
from sonogym.envs.imaging import NetChoice
from sonogym.envs.patients import resolve_patients
from sonogym.envs.scene_config import SceneConfig
from sonogym.memory import return_freed_memory
from sonogym.ultrasound import ProbeGeometry, Slicer
from sonogym.ultrasound import randomization as imaging_rand
from sonogym.ultrasound.compression import MAX_CONTACT_FORCE, TissueCompression, probe_footprint
from sonogym.ultrasound.registry import SimulatorOptions, check_options
from sonogym.ultrasound.slicer import PatientCrop

#: CT window of the "ct" observation mode, HU -> [0, 1].
CT_WINDOW = (-1000.0, 2000.0)

#: m added to the range of probe-face positions: the reached pose may trail the clamped command.
REACH_MARGIN = 0.015
#: m added on every side of the box of image pixels: the skin between the lattice nodes the box
#: is taken on, and the reached pose off the skin. Random bang-bang actions over 600 steps came
#: no closer than 29.5 mm to a box with 15 mm here.
BOX_MARGIN = 0.005
#: rad a probe arm may tilt the beam beyond the task's own tilt (tracking, settling).
ARM_TILT_MARGIN = 0.1
#: N of contact force per unit of a force action (``force_action``), and the most one step
#: changes it: a force action's useful range is +-2, as the probe tasks' motion actions' is.
FORCE_ACTION_SCALE = 1.0
FORCE_ACTION_LIMIT = 2.0


@dataclass(frozen=True)
class ImagingReach:
    """Where a task's probe can be: its face on the skin within ``half_extent`` (m) in x and z
    of the point above the target vertebra's centre (with ``aimed``: of the skin point whose
    beam passes through that centre, ``SkinSurface.aim``), its beam within ``tilt`` (rad) of
    the skin's inward normal there, any yaw."""

    half_extent: float
    tilt: float = 0.0
    aimed: bool = False
    extra_depth: float = 0.0  # m the images may reach below their last row (tissue compression)


def imaging_reach_boxes(
    skin: SkinSurface, centres: np.ndarray, reach: ImagingReach, probe: ProbeGeometry,
    grid: float = 0.002,
) -> list[tuple[np.ndarray, np.ndarray]]:  # fmt: skip
    """Per patient, the (lo, hi) box of {P} (m) that contains every pixel of every probe image
    within ``reach`` (its face positions widened by ``REACH_MARGIN``, the box by
    ``BOX_MARGIN``, the depth by ``reach.extra_depth``): what a slicer must keep
    (``Slicer(crop_boxes=)``).

    For a face centre s with beam n (unit), a pixel lies at s + d n + q, 0 <= d <= depth and q
    in the plane normal to n with |q| <= r (r: half the diagonal of the array and elevation
    extents), so along axis k it lies within s_k + [min(0, depth n_k), max(0, depth n_k)]
    +- r sin(angle(n, e_k)). The bound is taken over the skin on a ``grid`` (m) lattice of the
    reach square, with n anywhere in the cone of half-angle ``tilt`` around the normal."""
    half = reach.half_extent + REACH_MARGIN
    u = np.arange(-half, half + grid / 2, grid)
    r = float(np.hypot(probe.width / 2, probe.elevation_px * probe.elevation_spacing / 2))
    depth = probe.depth + reach.extra_depth
    boxes = []
    for p, c in enumerate(np.asarray(centres, dtype=np.float64)):
        cx, cz = c[0], c[2]
        if reach.aimed:
            target = torch.as_tensor(c, dtype=torch.float64, device=skin.device)
            ax, az = skin.aim(target, torch.tensor(p, device=skin.device))
            cx, cz = float(ax), float(az)
        gx, gz = np.meshgrid(cx + u, cz + u, indexing="ij")
        x = torch.as_tensor(gx.ravel(), dtype=torch.float32)
        z = torch.as_tensor(gz.ravel(), dtype=torch.float32)
        idx = torch.full_like(x, p, dtype=torch.long)
        y = skin.height(x.to(skin.device), z.to(skin.device), idx.to(skin.device)).cpu()
        n = skin.normal(x.to(skin.device), z.to(skin.device), idx.to(skin.device)).cpu()
        s = torch.stack([x, y, z], -1).double().numpy()
        ang = np.arccos(np.clip(n.double().numpy(), -1, 1))  # (M, 3): angle of n to each axis
        a_lo, a_hi = np.clip(ang - reach.tilt, 0, np.pi), np.clip(ang + reach.tilt, 0, np.pi)
        n_lo, n_hi = np.cos(a_hi), np.cos(a_lo)  # range of n_k over the cone
        sin_max = np.where((a_lo <= np.pi / 2) & (a_hi >= np.pi / 2), 1.0,
                           np.maximum(np.sin(a_lo), np.sin(a_hi)))  # fmt: skip
        lo = s + np.minimum(0, depth * n_lo) - r * sin_max
        hi = s + np.maximum(0, depth * n_hi) + r * sin_max
        boxes.append((lo.min(0) - BOX_MARGIN, hi.max(0) + BOX_MARGIN))
    return boxes


class PatientScene:
    """Patients + imaging for N envs (see the module docstring).

    Args:
        cfg: the task's ``SceneConfig`` (``patients``, ``phantom_spacing``, ``simulator``,
            ``learned_nets``, ``learned_precision``, ``target_vertebra``): ``simulator`` names
            a registered simulator (``sonogym.ultrasound.registry``); with one that
            ``draws_net`` (the learned one) each env uses ``nets.index`` into
            ``learned_nets``, redrawn by ``draw_nets`` at its resets; ``target_vertebra``'s
            body centroid anchors goals and arm placement.
        num_envs: N.
        device: torch device of everything.
        probe: the imaging geometry.
        gel_depth: m, coupling gel under the probe face, overriding the ultrasound
            model's (None keeps the model's).
        reach: where the task's probe can be; the slicer then keeps only what it can image
            (``imaging_reach_boxes``); None keeps the whole volumes.
        keep_volumes: True: load every patient whole first (for tasks that read the volumes
            while they build, and the learned simulator's intensity matching). False: the task
            reads volumes only through the slicer, so each patient is loaded, cropped for the
            slicer (``PatientCrop``) and reduced to its ``PatientModel`` before the next one
            loads: building never holds all full volumes at once (the same slicer, the same
            images).
    """

    def __init__(
        self,
        cfg: SceneConfig,
        num_envs: int,
        device: torch.device,
        probe: ProbeGeometry,
        gel_depth: float | None = None,
        reach: ImagingReach | None = None,
        keep_volumes: bool = True,
    ) -> None:
        patients, spacing, simulator = cfg.patients, cfg.phantom_spacing, cfg.simulator
        learned_nets, learned_precision = cfg.learned_nets, cfg.learned_precision
        target_vertebra = cfg.target_vertebra
        self.simulator_options = SimulatorOptions(tuple(learned_nets), learned_precision, gel_depth)
        #: whether the probe's contact force compresses the tissue (``contact_force`` > 0, or a
        #: force action); off, imaging takes exactly the static model's path
        self.compresses_tissue = cfg.compresses_tissue
        self.initial_force = float(cfg.contact_force)  # N
        self.force_limit = float(cfg.force_limit)  # N
        if self.compresses_tissue and reach is not None:  # compressed images reach deeper
            model = TissueCompression(probe)
            reach = replace(reach, extra_depth=model.max_shift(MAX_CONTACT_FORCE))
        #: the simulator's registry entry (what it needs, how it is built)
        self.simulator_spec = check_options(simulator, self.simulator_options)
        #: whether each env's learned net is drawn at its resets (``draw_nets``): the task
        #: draws it after its own draws, so a seed gives the same episode with any simulator
        self.draws_nets = self.simulator_spec.draws_net
        self.reach = reach
        self.learned_precision = learned_precision
        self.device = device
        self.num_envs = num_envs
        self.simulator_name = self.simulator_spec.name
        self.learned_nets = tuple(learned_nets)
        self.nets = NetChoice(num_envs, len(self.learned_nets), device)
        self.probe_geometry = probe
        self.gel_depth = gel_depth
        self._crops: list[PatientCrop] | None = None
        if keep_volumes or self.simulator_spec.needs_volumes:
            self.patients = resolve_patients(patients, spacing)
        else:
            self.patients, self._crops = self._load_cropped(patients, spacing, target_vertebra)
        self.patient_index = torch.arange(num_envs, device=device) % len(self.patients)
        self.skin = SkinSurface.stack([p.skin for p in self.patients]).to(device)
        centres = np.array([p.landmarks.vertebra(target_vertebra).centre for p in self.patients])
        #: (P, 3) float64 and (N, 3) float32: the target vertebra's body centroid in {P}, m.
        self.target_centres_p = torch.tensor(centres, dtype=torch.float64, device=device)
        self.target_centres = self.target_centres_p[self.patient_index].float()
        self.probe_pos = torch.zeros(num_envs, 3, device=device)
        self.probe_rot = torch.eye(3, device=device).repeat(num_envs, 1, 1)
        #: (N,) float32, N: each env's probe contact force (``initial_force`` at its resets)
        self.contact_force = torch.full((num_envs,), self.initial_force, device=device)
        #: Per-episode imaging settings (``randomize_imaging``); None: images as simulated.
        self.imaging_randomization: imaging_rand.ImagingRandomization | None = None
        self.imaging_settings: torch.Tensor | None = None

    def _load_cropped(self, specs, spacing: float, target_vertebra: str):
        """([PatientModel], [PatientCrop]): each patient loaded, cropped for the slicer and
        released before the next loads (``keep_volumes=False``)."""
        specs = [specs] if isinstance(specs, int | str | Path) else list(specs)
        if not specs:
            resolve_patients(specs, spacing)  # raises the usual error
        models, crops = [], []
        for spec in specs:
            patient = resolve_patients([spec], spacing)[0]
            box = None
            if self.reach is not None:
                centre = patient.landmarks.vertebra(target_vertebra).centre
                skin = SkinSurface.stack([patient.skin]).to(self.device)
                box = imaging_reach_boxes(skin, centre[None], self.reach, self.probe_geometry)[0]
            crops.append(PatientCrop.of(patient, box))
            models.append(patient.model())
            del patient
            return_freed_memory()
        return models, crops

    # ---------------------------------------------------------------- imaging
    @cached_property
    def slicer(self) -> Slicer:
        if self._crops is not None:  # patients loaded one at a time (keep_volumes=False)
            crops, self._crops = self._crops, None
            return Slicer(crops, self.probe_geometry, device=self.device)
        boxes = None
        if self.reach is not None:
            centres = self.target_centres_p.cpu().numpy()
            boxes = imaging_reach_boxes(self.skin, centres, self.reach, self.probe_geometry)
        return Slicer(self.patients, self.probe_geometry, device=self.device, crop_boxes=boxes)

    @cached_property
    def tissue(self) -> TissueCompression | None:
        """The tissue compression on the slicer's sampling grid (None: static tissue)."""
        if not self.compresses_tissue:
            return None
        return TissueCompression(self.probe_geometry, self.slicer.block, device=self.device)

    @cached_property
    def _beam(self) -> tuple[Slicer, TissueCompression]:
        """The slicer and compression model of the beam under the image's centre (the
        compression ``info`` reports, imaged or not)."""
        pr = self.probe_geometry
        beam = ProbeGeometry(pr.depth_px, 1, 1, pr.depth_spacing, pr.width_spacing)
        slicer = self.slicer.sharing(beam, (self.slicer.block[0], 1))
        model = TissueCompression(beam, slicer.block, probe_footprint(pr), self.tissue.params,
                                  self.device, (self.tissue.stride[0], 1))  # fmt: skip
        return slicer, model

    def centre_compression(self, env_ids: torch.Tensor | None = None) -> torch.Tensor:
        """(K,) float32, m: how much the tissue under the image's centre is compressed at the
        reached probe poses of ``env_ids`` (None: all); zeros with static tissue."""
        sl = slice(None) if env_ids is None else env_ids
        if self.tissue is None:
            return torch.zeros_like(self.contact_force[sl])
        slicer, model = self._beam
        warp = model.bind(self.contact_force[sl], MAX_CONTACT_FORCE)
        slicer.shifts(self.probe_pos[sl], self.probe_rot[sl], warp, self.patient_index[sl])
        return warp.centre

    def reset_force(self, env_ids: torch.Tensor) -> None:
        """The contact force of ``env_ids`` back to the config's ``contact_force``."""
        self.contact_force[env_ids] = self.initial_force

    def step_force(self, action: torch.Tensor) -> None:
        """One force action (N,) per env, unitless: the force changes by ``FORCE_ACTION_SCALE``
        N per unit, clipped to +-``FORCE_ACTION_LIMIT`` N per step, and stays within [0,
        ``MAX_CONTACT_FORCE``] N (documented clamps)."""
        delta = (action * FORCE_ACTION_SCALE).clamp(-FORCE_ACTION_LIMIT, FORCE_ACTION_LIMIT)
        self.contact_force = (self.contact_force + delta).clamp(0.0, MAX_CONTACT_FORCE)

    def tissue_info(self) -> dict[str, torch.Tensor]:
        """What ``info`` reports of the contact force when it compresses the tissue (else
        nothing): ``contact_force`` (N,) N; ``compression_mm`` (N,), the tissue under the
        image's centre compressed this much; ``force_cost`` (N,) float32, 1 where the force
        exceeds ``force_limit``."""
        if self.tissue is None:
            return {}
        force = self.contact_force.clone()
        return {
            "contact_force": force,
            "compression_mm": self.centre_compression() * 1e3,
            "force_cost": (force > self.force_limit).float(),
        }

    @cached_property
    def simulator(self):
        """The ``UltrasoundSimulator`` of ``simulator_spec``, built for the patients."""
        spec = self.simulator_spec
        return spec.build(list(self.patients), torch.device(self.device), self.simulator_options)

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

    def randomize_imaging(self, value) -> None:
        """Display each episode's images with settings drawn from ``value``'s ranges (a
        config's ``imaging_randomization``; ``sonogym.ultrasound.randomization``), redrawn
        per env by ``draw_imaging`` at its resets; False / None: images as simulated."""
        self.imaging_randomization = imaging_rand.imaging_ranges(value)
        self.imaging_settings = None
        if self.imaging_randomization is not None:
            self.imaging_settings = imaging_rand.nominal(
                self.num_envs, self.probe_geometry, self.simulator_spec.dynamic_range, self.device
            )

    def draw_imaging(self, env_ids: torch.Tensor, u: torch.Tensor) -> None:
        """New imaging settings for ``env_ids`` from uniforms ``u`` (K, 8) in [0, 1)."""
        if self.imaging_randomization is not None:
            self.imaging_settings[env_ids] = self.imaging_randomization.draw(
                u.to(self.device, torch.float32)
            )

    def draw_nets(self, env_ids: torch.Tensor, u: torch.Tensor) -> None:
        """Draw the learned net of each env in ``env_ids`` from uniforms ``u`` (see NetChoice)."""
        self.nets.draw(env_ids, u)

    @property
    def image_shape(self) -> tuple[int, ...]:
        """(E, H, W) of the probe's images."""
        return self.probe_geometry.shape

    def slices(self, env_ids: torch.Tensor | None = None):
        """CT and label slices at the reached probe poses of ``env_ids`` (None: all), with each
        env's learned net (``Slices.net_index``; the model-based simulators ignore it)."""
        sl = slice(None) if env_ids is None else env_ids
        warp = None
        if self.tissue is not None:
            warp = self.tissue.bind(self.contact_force[sl], MAX_CONTACT_FORCE)
        s = self.slicer(self.probe_pos[sl], self.probe_rot[sl], self.patient_index[sl], warp=warp)
        return replace(s, net_index=self.nets.index[sl])

    def observe(self, mode: str, env_ids: torch.Tensor | None = None) -> torch.Tensor:
        """An image observation of the reached probe poses of ``env_ids`` (None: all),
        (K, E, H, W): "us" the ultrasound of ``simulator`` in [0, 1] (built only for this mode;
        the learned one images each env with its own net), with the episode's imaging settings
        when ``randomize_imaging`` is on; "ct" the CT windowed from ``CT_WINDOW`` to [0, 1];
        "labels" the uint8 ids."""
        if mode not in ("us", "ct", "labels"):
            raise ValueError(f"unknown image mode {mode!r}")
        slices = self.slices(env_ids)
        if mode == "ct":
            lo, hi = CT_WINDOW
            return ((slices.ct - lo) / (hi - lo)).clamp(0, 1)
        if mode == "labels":
            return slices.labels
        if self.imaging_randomization is None:
            return self.simulator.simulate(slices).float()
        settings = self.imaging_settings
        settings = settings if env_ids is None else settings[env_ids]
        return self.simulator_spec.randomized(self.simulator, slices, settings, self.probe_geometry)
