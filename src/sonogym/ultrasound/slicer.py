"""Batched slicing of CT and label volumes along probe image planes.

``Slicer(patients, probe)(pos, rot)`` samples, for N probe poses in the patient frame {P}, the CT
(trilinear, Hounsfield units) and the label map (nearest) on every pixel of the probe's grid
(``ProbeGeometry``): arrays of shape (N, E, H, W). One call serves envs spread over several
patients: the patients' volumes live in one flat buffer, each env gathers from its own patient
with flat indices (no Python loop over envs, no ``grid_sample``: flat gathers are ~5x faster on
CPU). Anything outside a patient's volume reads as air (-1000 HU, label 0): the buffers carry a
one-voxel air border, and coordinates are clamped into it.

Sampling at the volume's resolution (``upsample=True``, the default): when the image pixels are
finer than the voxels (0.5 mm pixels, 1 mm voxels), the slicer samples the volume on a grid of
k x k pixel blocks, k = floor(voxel / pixel), at the block centres, and upsamples to the pixel
grid: bilinearly for CT, by block replication for labels (so each pixel takes the label of the
sample nearest to it, at most (k - 1) / 2 pixels away). Trilinear interpolation of a voxel grid
has no detail finer than a voxel, so this is 4x cheaper at k = 2 and indistinguishable in the
``physical`` model's images (image correlation > 0.97 with direct sampling,
tests/ultrasound/test_slicer.py). The ``sonogym`` model squares per-pixel CT jumps, so its bone
lines change brightness with how an edge's ramp is sampled (as the reference's did with its
nearest-voxel lookup): same structures, correlation > 0.9, line brightness within ~30 %.
``upsample=False`` samples every pixel directly.

Cropping (``crop_boxes``): a slicer may hold, per patient, only the box of the patient frame
that the task's probes can image (``sonogym.envs.scene.imaging_reach_boxes``); outside it reads
as air like outside the volume. Images are unchanged as long as every image stays inside the
box, which each call checks (``expect_all``: at once on CPU, queued on CUDA) on the corners of
every image plane, on the sides where the box cuts the volume.

Gathers run depth-first along the volume's contiguous axis (y, the beam's usual direction) in
chunks of envs that fit in cache, with int32 indices and ``index_select`` (3-5x faster than
``take``/advanced indexing on CPU), and all temporaries live in reused buffers. With more than
one torch thread on CPU the chunks run on that many threads at once (``ChunkRunner``; same
images).
"""

from __future__ import annotations

import copy
import zlib
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import torch

from sonogym.anatomy.patient import Patient
from sonogym.checks import expect_all
from sonogym.memory import return_freed_memory
from sonogym.ultrasound._packed_labels import (
    BLOCK,
    PALETTE,
    gather_labels,
    pack_labels,
    unpack_labels,
)
from sonogym.ultrasound._workspace import ChunkRunner, Workspace
from sonogym.ultrasound.probe import ProbeGeometry

#: Value of anything outside a patient's volume.
AIR_HU = -1000.0


@dataclass(frozen=True, eq=False)
class Slices:
    """CT and label samples on N probes' pixel grids, plus where those pixels are.

    Attributes:
        ct: (N, E, H, W) float32, Hounsfield units.
        labels: (N, E, H, W) uint8, ids of ``sonogym.anatomy.labels``.
        origin: (N, E, 3) float64, patient-frame position (m) of pixel (row 0, column 0) of
            each elevation slice.
        row_step: (N, 3) float64, patient-frame displacement (m) from one row to the next
            (depth_spacing * z_U).
        col_step: (N, 3) float64, displacement (m) from one column to the next
            (width_spacing * x_U).
        seed: (N,) int64, speckle seed of each env's patient (speckle is a function of the
            patient-frame position and this seed only).
        patient_index: (N,) int64, index of each env's patient in the slicer.
        probe: the pixel grid.
        net_index: (N,) int64 or None, the learned net that images each env (an index into a
            ``LearnedSimulator``'s nets; the slicer leaves it None, a scene sets it with
            ``dataclasses.replace``). Model-based simulators ignore it; a learned simulator
            given None picks one net for the whole batch.
    """

    ct: torch.Tensor
    labels: torch.Tensor
    origin: torch.Tensor
    row_step: torch.Tensor
    col_step: torch.Tensor
    seed: torch.Tensor
    patient_index: torch.Tensor
    probe: ProbeGeometry
    net_index: torch.Tensor | None = None

    @property
    def num_envs(self) -> int:
        return self.ct.shape[0]

    @property
    def device(self) -> torch.device:
        return self.ct.device

    def positions(self) -> torch.Tensor:
        """(N, E, H, W, 3) float32 patient-frame position of every pixel, metres (not used on
        the hot path; for tests and tools)."""
        _, _, h, w = self.ct.shape
        j = torch.arange(h, dtype=torch.float64, device=self.device)
        i = torch.arange(w, dtype=torch.float64, device=self.device)
        p = (
            self.origin[:, :, None, None, :]
            + j[None, None, :, None, None] * self.row_step[:, None, None, None, :]
            + i[None, None, None, :, None] * self.col_step[:, None, None, None, :]
        )
        return p.float()

    def select(self, index: torch.Tensor | slice | int) -> Slices:
        """The slices of a subset of envs (same pixel grid)."""
        if isinstance(index, int):
            index = slice(index, index + 1)
        return Slices(
            self.ct[index],
            self.labels[index],
            self.origin[index],
            self.row_step[index],
            self.col_step[index],
            self.seed[index],
            self.patient_index[index],
            self.probe,
            None if self.net_index is None else self.net_index[index],
        )

    @staticmethod
    def cat(parts: Sequence[Slices]) -> Slices:
        """Concatenate slices of the same probe along the env axis."""
        if not parts:
            raise ValueError("Slices.cat needs at least one Slices")
        probe = parts[0].probe
        if any(p.probe != probe for p in parts):
            raise ValueError("Slices.cat: all parts must share one ProbeGeometry")
        nets = [p.net_index for p in parts]
        if any(n is None for n in nets) and any(n is not None for n in nets):
            raise ValueError("Slices.cat: give every part a net_index, or none")
        return Slices(
            *(torch.cat([getattr(p, f) for p in parts]) for f in _TENSOR_FIELDS),
            probe=probe,
            net_index=None if nets[0] is None else torch.cat(nets),
        )


_TENSOR_FIELDS = ("ct", "labels", "origin", "row_step", "col_step", "seed", "patient_index")


class DepthWarp(Protocol):
    """Moves a slicer's samples along their beams (``Slicer.__call__(warp=)``; the tissue
    compression of ``sonogym.ultrasound.compression`` is one).

    It works on a grid ``stride`` = (sd, sl) times coarser than the slicer's samples (blocks of
    ``Slicer.block`` times ``stride`` pixels, sampled at their centres). Called once per chunk
    of envs with the labels of that grid, undeformed, (n, E, Wc', Hc') uint8 (depth last), the
    chunk's env slice and the chunk's scratch ``Workspace``; returns how many of its rows
    deeper each point shows, (n, E, Wc', Hc') float32 >= 0, at most ``max_rows`` (the crop
    check's reach), or None: nothing moves. The slicer interpolates that to its samples
    (linearly, as it upsamples CT). A shift of exactly 0 samples the same point, bit for bit."""

    stride: tuple[int, int]
    max_rows: int

    def __call__(self, labels: torch.Tensor, envs: slice, ws: Workspace) -> torch.Tensor | None: ...


def speckle_seed(patient: Patient) -> int:
    """A patient's speckle seed: ``meta['speckle_seed']`` if set (loaded subjects carry a hash
    of their content there), else a stable hash of its name (phantoms: "phantom-<seed>"), so
    the same patient always shows the same speckle. Names from the file system may hold
    surrogate-escaped bytes (non-UTF-8 folder names): they are hashed as such, never rejected."""
    seed = patient.meta.get("speckle_seed") if isinstance(patient.meta, dict) else None
    if isinstance(seed, bool) or not hasattr(seed, "__index__"):  # ints and numpy ints only
        seed = zlib.crc32(str(patient.name).encode("utf-8", "surrogatepass"))
    return int(seed) & 0x7FFFFFFF


def check_poses(pos: torch.Tensor, rot: torch.Tensor) -> None:
    """Raise a clear error unless pos is (N, 3) and rot (N, 3, 3), both finite."""
    if not isinstance(pos, torch.Tensor) or not isinstance(rot, torch.Tensor):
        raise TypeError("probe poses must be torch tensors: pos (N, 3) and rot (N, 3, 3)")
    if pos.ndim != 2 or pos.shape[-1] != 3:
        raise ValueError(f"probe positions must have shape (N, 3), got {tuple(pos.shape)}")
    if rot.shape != (pos.shape[0], 3, 3):
        raise ValueError(
            f"probe rotations must have shape (N, 3, 3) = ({pos.shape[0]}, 3, 3) to match the "
            f"positions, got {tuple(rot.shape)}"
        )

    def detail() -> str:
        bad = (~torch.isfinite(pos).all(-1)) | (~torch.isfinite(rot).flatten(1).all(-1))
        return f"probe poses contain NaN/inf (envs {bad.nonzero().flatten().tolist()[:10]})"

    expect_all(torch.isfinite(pos).all(-1) & torch.isfinite(rot).flatten(1).all(-1), detail)


def _crop_range(patient: Patient, box) -> tuple[list[tuple[int, int]], np.ndarray]:
    """([(first, end) voxel range per axis], (2, 3) limits in {P} that images must stay in)
    of the part of ``patient`` a slicer keeps for crop box ``box`` (None: all of it).

    The range covers the box plus one voxel (a sample inside the box interpolates from the next
    voxel); the limits are the box on each side where the range cuts the volume and +-inf
    where it does not (there, what lies beyond is outside the volume, air either way)."""
    shape = patient.shape
    lim = np.array([[-np.inf] * 3, [np.inf] * 3])
    if box is None:
        return [(0, n) for n in shape], lim
    lo, hi = (np.asarray(b, dtype=np.float64).reshape(3) for b in box)
    if not (np.isfinite(lo).all() and np.isfinite(hi).all() and (lo < hi).all()):
        raise ValueError(f"crop box must have finite corners lo < hi, got {lo} and {hi}")
    sp, org = np.asarray(patient.spacing), np.asarray(patient.origin)
    first = np.floor((lo - org) / sp).astype(int) - 1
    end = np.ceil((hi - org) / sp).astype(int) + 2
    keep = []
    for k, n in enumerate(shape):
        a, b = max(0, int(first[k])), min(n, int(end[k]))
        if a >= b:  # the box misses the volume on this axis: keep one voxel, all reads are air
            a, b = (0, 1) if first[k] < 0 else (n - 1, n)
        keep.append((a, b))
        if a > 0:
            lim[0, k] = lo[k]
        if b < n:
            lim[1, k] = hi[k]
    return keep, lim


def _fill_box(flat: torch.Tensor, dims, volume: torch.Tensor, keep) -> None:
    """Write the ``keep`` ranges of ``volume`` (x, y, z) inside the one-voxel border of the
    padded box of ``dims`` that starts ``flat``, stored in the slicer's memory order (X, Z, Y)."""
    dx, dy, dz = dims
    box = flat[: dx * dy * dz].view(dx, dz, dy).permute(0, 2, 1)  # (x, y, z) view
    box[1:-1, 1:-1, 1:-1] = volume[tuple(slice(a, b) for a, b in keep)].to("cpu")


@dataclass(eq=False)
class PatientCrop:
    """The part of one patient a ``Slicer`` keeps, already in its layout: the kept box with a
    one-voxel air border in the (X, Z, Y) memory order, padded to whole label blocks.

    Built from a loaded patient by ``PatientCrop.of`` (about 2.5 bytes per kept voxel), so an
    env over many patients can load them one at a time, keep each one's crop and release its
    full volumes (5 bytes per voxel of the whole scan) before loading the next
    (``sonogym.envs.scene.PatientScene``). A ``Slicer`` built from crops moves their buffers
    into its own and leaves the crops empty (``released``).

    Attributes:
        name: the patient's name.
        dims: padded (x, y, z) box size, voxels.
        ct: (span,) float16 HU, air in the border and after the box.
        labels: (span,) uint8 ids, or (span / 2,) nibbles when ``palette`` is set (packed).
        palette: None, or (span / BLOCK * PALETTE,) uint8 (``pack_labels``).
        origin: (3,) {P} position (m) of padded voxel 0.
        spacing: (3,) m per voxel.
        seed: the patient's speckle seed (``speckle_seed``).
        lim: (2, 3) {P} limits images must stay in (+-inf where the box does not cut).
    """

    name: str
    dims: tuple[int, int, int]
    ct: torch.Tensor
    labels: torch.Tensor
    palette: torch.Tensor | None
    origin: np.ndarray
    spacing: np.ndarray
    seed: int
    lim: np.ndarray

    @classmethod
    def of(cls, patient: Patient, box=None, packed_labels: bool = True) -> PatientCrop:
        """Crop ``patient`` to ``box`` ((lo, hi) corners in {P}, m; None: keep it whole);
        labels packed at 4 bits per voxel where every block holds at most 16 labels."""
        if not isinstance(patient, Patient):
            raise TypeError(
                f"PatientCrop.of needs a Patient with its volumes, got {type(patient).__name__}"
            )
        keep, lim = _crop_range(patient, box)
        dims = tuple(b - a + 2 for a, b in keep)
        span = -(-int(np.prod(dims)) // BLOCK) * BLOCK
        ct = torch.full((span,), AIR_HU, dtype=torch.float16)
        _fill_box(ct, dims, patient.ct, keep)
        labels = torch.zeros(span, dtype=torch.uint8)
        _fill_box(labels, dims, patient.labels, keep)
        packed = pack_labels(labels) if packed_labels else None
        first = np.array([a for a, _ in keep], dtype=np.float64)
        sp = np.asarray(patient.spacing, dtype=np.float64)
        return cls(
            name=patient.name,
            dims=dims,
            ct=ct,
            labels=labels if packed is None else packed[0],
            palette=None if packed is None else packed[1],
            origin=patient.origin + (first - 1) * sp,  # one voxel before the first kept
            spacing=sp,
            seed=speckle_seed(patient),
            lim=lim,
        )

    @property
    def span(self) -> int:
        """Voxels of the padded run."""
        return self.ct.numel()

    @property
    def released(self) -> bool:
        """True once a Slicer has taken the buffers (a crop always spans at least one block)."""
        return self.ct.numel() == 0

    def label_bytes(self) -> torch.Tensor:
        """The labels as one uint8 id per voxel (unpacked if packed)."""
        if self.palette is None:
            return self.labels
        return unpack_labels(self.labels, self.palette)

    def release(self) -> None:
        """Drop the buffers (a Slicer has copied them)."""
        empty = torch.empty(0, dtype=torch.uint8)
        self.ct, self.labels = torch.empty(0, dtype=torch.float16), empty
        self.palette = None if self.palette is None else empty


def upsample_linear(src: torch.Tensor, dim: int, k: int, out: torch.Tensor) -> torch.Tensor:
    """Linear upsampling by an integer factor k along ``dim`` into ``out`` (size n * k there).

    Output sample m * k + r sits at source coordinate m + (r + 0.5) / k - 0.5 (sample centres
    aligned, like ``F.interpolate(..., align_corners=False)``), clamped at the edges."""
    n = src.shape[dim]
    shape = list(out.shape)
    ov = (
        out.view(*shape[:dim], n, k, *shape[dim + 1 :])
        if dim != -1
        else out.view(*shape[:-1], n, k)
    )
    d = dim if dim >= 0 else src.ndim + dim
    for r in range(k):
        t = (r + 0.5) / k - 0.5
        o = ov.select(d + 1, r)
        if t == 0 or n == 1:
            o.copy_(src)
        elif t > 0:  # between m and m + 1
            torch.lerp(
                src.narrow(d, 0, n - 1), src.narrow(d, 1, n - 1), t, out=o.narrow(d, 0, n - 1)
            )
            o.narrow(d, n - 1, 1).copy_(src.narrow(d, n - 1, 1))
        else:  # between m - 1 and m
            torch.lerp(
                src.narrow(d, 1, n - 1), src.narrow(d, 0, n - 1), -t, out=o.narrow(d, 1, n - 1)
            )
            o.narrow(d, 0, 1).copy_(src.narrow(d, 0, 1))
    return out


class Slicer:
    """Sample CT and labels of several patients on N probes' pixel grids in one batched call.

    Args:
        patients: one Patient or a sequence of them; or ``PatientCrop``s (built one patient at
            a time, see there), whose buffers the slicer takes over.
        probe: the pixel grid (default: the paper's 2-D linear probe).
        device: where the volumes and the outputs live (default: the first patient's CT's).
        upsample: sample at the volume's resolution and upsample to finer pixels (see the module
            docstring); False samples every pixel.
        chunk_samples: volume samples per chunk of envs (bounds the scratch memory and keeps it
            in cache); default 2**17 on CPU, everything at once on CUDA.
        crop_boxes: per patient, None (keep the whole volume) or (lo, hi), two (3,) corners in
            {P} (m) of the region to keep; see the module docstring. None for a PatientCrop.
        packed_labels: hold labels at 4 bits per voxel with a palette per block of 512 voxels
            (``sonogym.ultrasound._packed_labels``; exact, falls back to bytes by itself where a
            block holds more than 16 labels); False keeps one byte per voxel.

    Memory: a padded copy of every patient, CT as float16 (HU to 0.5 HU below 1024 HU, 1 HU
    to 2048, 2 HU above) and labels packed (about 0.53 bytes per voxel, 1 if unpacked):
    2.53 bytes per voxel, plus reusable scratch buffers (about 80 bytes per sample of one
    chunk: 10 MB on CPU).
    """

    def __init__(
        self,
        patients: Patient | Sequence[Patient],
        probe: ProbeGeometry | None = None,
        device: torch.device | str | None = None,
        upsample: bool = True,
        chunk_samples: int | None = None,
        crop_boxes: Sequence[tuple[np.ndarray, np.ndarray] | None] | None = None,
        packed_labels: bool = True,
    ) -> None:
        if isinstance(patients, Patient | PatientCrop):
            patients = [patients]
        patients = list(patients)
        if not patients or not all(isinstance(p, Patient | PatientCrop) for p in patients):
            raise TypeError(
                "Slicer needs one Patient (or PatientCrop) or a non-empty sequence of them"
            )
        self.probe = probe if probe is not None else ProbeGeometry.linear_2d()
        if not isinstance(self.probe, ProbeGeometry):
            raise TypeError(f"probe must be a ProbeGeometry, got {type(self.probe).__name__}")
        if device is None:
            first = patients[0]
            device = first.ct.device if isinstance(first, Patient) else "cpu"
        self.device = torch.device(device)
        self.upsample = bool(upsample)
        if chunk_samples is None:
            chunk_samples = 2**17 if self.device.type == "cpu" else 2**40
        self.chunk_samples = int(chunk_samples)

        if crop_boxes is None:
            crop_boxes = [None] * len(patients)
        if len(crop_boxes) != len(patients):
            raise ValueError(
                f"crop_boxes has {len(crop_boxes)} entries for {len(patients)} patients"
            )
        crops = []
        for p, box in zip(patients, crop_boxes, strict=True):
            if isinstance(p, PatientCrop):
                if box is not None:
                    raise ValueError(f"{p.name} is already a PatientCrop: give no crop box for it")
                if p.released:
                    raise ValueError(f"{p.name}: this PatientCrop went into another Slicer")
                crops.append(p)
            else:  # cropped one at a time, each copied into the buffers below and dropped
                crops.append(PatientCrop.of(p, box, packed_labels))
        del patients  # the crops of Patients are the only copies: released as they are copied
        self.names = [c.name for c in crops]
        dims = [c.dims for c in crops]
        spans = [c.span for c in crops]
        offs = np.concatenate([[0], np.cumsum(spans)[:-1]]).astype(np.int64).tolist()
        total = sum(spans)
        if total >= 2**31:
            raise ValueError(f"Slicer: {total} voxels in all; at most 2**31 fit one slicer")
        orgs = [c.origin for c in crops]
        sps = [c.spacing for c in crops]
        seeds = [c.seed for c in crops]
        lims = [c.lim for c in crops]
        # One flat buffer per volume type. Each crop covers its span whole, so torch.empty's
        # pages are first touched by the copy, and each crop is released right after it: the
        # build holds about one copy of the compact volumes, not two.
        self.labels_packed = bool(packed_labels) and all(c.palette is not None for c in crops)
        flat_ct = torch.empty((total,), dtype=torch.float16)
        if self.labels_packed:
            nibbles = torch.empty(total // 2, dtype=torch.uint8)
            palette = torch.empty(total // BLOCK * PALETTE, dtype=torch.uint8)
        else:
            flat_lab = torch.empty((total,), dtype=torch.uint8)
        for c, off, span in zip(crops, offs, spans, strict=True):
            flat_ct[off : off + span] = c.ct
            if self.labels_packed:
                nibbles[off // 2 : (off + span) // 2] = c.labels
                palette[off // BLOCK * PALETTE : (off + span) // BLOCK * PALETTE] = c.palette
            else:
                flat_lab[off : off + span] = c.label_bytes()
            c.release()
            return_freed_memory()  # the crop's heap pages back to the OS before the next copy
        dev = self.device
        self._ct = flat_ct.to(dev)
        if self.labels_packed:
            self._nibbles, self._palette = nibbles.to(dev), palette.to(dev)
        else:
            self._lab = flat_lab.to(dev)
        dims_t = torch.tensor(dims, dtype=torch.int64)
        self._dmax = (dims_t - 2).to(dev, torch.float32)  # (P, 3) largest lower-corner index
        # strides of (x, y, z) in the (X, Z, Y) memory order
        strides = torch.stack(
            [dims_t[:, 1] * dims_t[:, 2], torch.ones_like(dims_t[:, 0]), dims_t[:, 1]], 1
        )
        self._strides = strides.to(dev, torch.int32)  # (P, 3)
        self._offsets = torch.tensor(offs, dtype=torch.int32, device=dev)
        self._origin = torch.tensor(np.array(orgs), dtype=torch.float64, device=dev)  # (P, 3)
        self._spacing = torch.tensor(np.array(sps), dtype=torch.float64, device=dev)  # (P, 3)
        self._seeds = torch.tensor(seeds, dtype=torch.int64, device=dev)
        self._lim = torch.tensor(np.array(lims), dtype=torch.float64, device=dev)  # (P, 2, 3)
        self.cropped = bool(np.isfinite(np.array(lims)).any())
        self._chunks = ChunkRunner(dev)  # scratch buffers, one set per worker thread
        self._min_spacing = min(float(s.min()) for s in sps)
        self.block = self._block_for(self.probe)

    def _block_for(self, probe: ProbeGeometry) -> tuple[int, int]:
        """(kz, kx) pixels per sample of ``probe``'s grid (module docstring)."""
        if not self.upsample:
            return (1, 1)
        return (
            max(1, int(self._min_spacing / probe.depth_spacing + 1e-6)),
            max(1, int(self._min_spacing / probe.width_spacing + 1e-6)),
        )

    def sharing(self, probe: ProbeGeometry, block: tuple[int, int] | None = None) -> Slicer:
        """A slicer of another pixel grid over this one's volumes (shared, not copied), with
        ``block`` pixels per sample (None: as this slicer would choose)."""
        other = copy.copy(self)
        other.probe = probe
        other.block = tuple(block) if block is not None else self._block_for(probe)
        other._chunks = ChunkRunner(self.device)
        return other

    @property
    def num_patients(self) -> int:
        return len(self.names)

    @property
    def num_voxels(self) -> int:
        """Voxels held, all patients (padding and block alignment included)."""
        return self._ct.numel()

    @property
    def nbytes(self) -> int:
        """Bytes held by the slicer: volume buffers and scratch."""
        if self.labels_packed:
            labels = self._nibbles.numel() + self._palette.numel()
        else:
            labels = self._lab.numel()
        return self._ct.numel() * 2 + labels + self._chunks.nbytes

    def default_patient_index(self, n: int) -> torch.Tensor:
        """Round-robin assignment of n envs to the patients (env i -> patient i % P)."""
        return torch.arange(n, device=self.device) % self.num_patients

    def _check_in_crop(self, origin, row_step, col_step, pidx, extra_rows: int = 0) -> None:
        """Every image plane's corners, the bottom ones ``extra_rows`` deeper (a warp's reach),
        inside its patient's crop box (on the cut sides): the images are convex, so then every
        pixel is."""
        pr = self.probe
        down = (pr.depth_px - 1 + extra_rows) * row_step[:, None, None, :]  # (N, 1, 1, 3)
        across = (pr.width_px - 1) * col_step[:, None, None, :]
        o = origin[:, :, None, :]  # (N, E, 1, 3)
        corners = torch.cat([o, o + down, o + across, o + down + across], 2)  # (N, E, 4, 3)
        lim = self._lim[pidx][:, None, None]  # (N, 1, 1, 2, 3)
        inside = (corners >= lim[..., 0, :]) & (corners <= lim[..., 1, :])
        expect_all(
            inside.flatten(1).all(1),
            lambda: (
                "a probe image leaves the region of its patient this slicer keeps "
                "(crop_boxes): the env's imaging reach is too small for this pose; build the env "
                "with crop_to_reach=False and report the pose"
            ),
        )

    # --------------------------------------------------------------- geometry
    def _geometry(
        self, pos: torch.Tensor, rot: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        pr = self.probe
        pos = pos.to(self.device, torch.float64)
        rot = rot.to(self.device, torch.float64)
        xu, yu, zu = rot[..., 0], rot[..., 1], rot[..., 2]
        x0 = -(pr.width_px - 1) / 2 * pr.width_spacing
        ye = pr.elevation_positions(self.device)  # (E,)
        origin = pos[:, None, :] + x0 * xu[:, None, :] + ye[None, :, None] * yu[:, None, :]
        return origin, zu * pr.depth_spacing, xu * pr.width_spacing

    # ---------------------------------------------------------------- slicing
    def __call__(
        self,
        pos: torch.Tensor,
        rot: torch.Tensor,
        patient_index: torch.Tensor | None = None,
        out: Slices | None = None,
        warp: DepthWarp | None = None,
    ) -> Slices:
        """Slice N probe poses.

        Args:
            pos: (N, 3) probe-face centres in {P}, metres.
            rot: (N, 3, 3) probe orientations in {P}; columns x_U, y_U, z_U.
            patient_index: (N,) int, which patient each env images (default round-robin).
            out: a previous result whose ct and labels tensors are overwritten (saves
                allocating them on every call).
            warp: sample deeper along each beam (``DepthWarp``: tissue compressed under the
                probe, ``sonogym.ultrasound.compression``); None samples the image planes as
                they are (the same code as without it).

        Returns:
            ``Slices`` with ct (N, E, H, W) float32 HU and labels (N, E, H, W) uint8.
        """
        check_poses(pos, rot)
        n = pos.shape[0]
        pidx = self._patient_index(n, patient_index)
        pr = self.probe
        shape = (n, pr.elevation_px, pr.depth_px, pr.width_px)
        if out is not None and out.ct.shape == shape and out.ct.device == self.device:
            ct, lab = out.ct, out.labels
        else:
            ct = torch.empty(shape, dtype=torch.float32, device=self.device)
            lab = torch.empty(shape, dtype=torch.uint8, device=self.device)
        origin, row_step, col_step = self._geometry(pos, rot)
        kz, kx = self.block
        if self.cropped:
            extra = 0 if warp is None else warp.max_rows * warp.stride[0] * kz
            self._check_in_crop(origin, row_step, col_step, pidx, extra)
        per_env = pr.elevation_px * -(-pr.depth_px // kz) * -(-pr.width_px // kx)
        step = max(1, self.chunk_samples // per_env)
        moved = None if warp is None else self._warp(warp, origin, row_step, col_step, pidx)

        def run(c: slice, ws: Workspace) -> None:
            shift = None if moved is None else (moved[c], warp.stride)
            self._sample(origin[c], row_step[c], col_step[c], pidx[c], ct[c], lab[c], ws, shift)

        # chunks of envs: bounded scratch, cache-sized on CPU
        self._chunks.run(run, [slice(s, min(n, s + step)) for s in range(0, n, step)])
        return Slices(ct, lab, origin, row_step, col_step, self._seeds[pidx], pidx, pr)

    def shifts(
        self,
        pos: torch.Tensor,
        rot: torch.Tensor,
        warp: DepthWarp,
        patient_index: torch.Tensor | None = None,
    ) -> torch.Tensor | None:
        """Only the warp's answer for N probe poses: its shifts on its own grid (N, E, Wc',
        Hc'; ``DepthWarp``), without sampling the images (None: nothing moves). The tissue
        compression reads its numbers this way (``CompressionWarp.centre``)."""
        check_poses(pos, rot)
        pidx = self._patient_index(pos.shape[0], patient_index)
        origin, row_step, col_step = self._geometry(pos, rot)
        return self._warp(warp, origin, row_step, col_step, pidx)

    def _patient_index(self, n: int, patient_index) -> torch.Tensor:
        """(n,) int64 patient of each env, checked (default round-robin)."""
        if patient_index is None:
            return self.default_patient_index(n)
        pidx = torch.as_tensor(patient_index, device=self.device).long().reshape(-1)
        if pidx.shape[0] != n:
            raise ValueError(f"patient_index must have shape ({n},), got {tuple(pidx.shape)}")
        expect_all(
            (pidx >= 0) & (pidx < self.num_patients),
            f"patient_index out of range: the slicer holds {self.num_patients} patients",
        )
        return pidx

    def _corners(self, a, b, shift, dvr, pidx, ws: Workspace):
        """Voxel indices of the samples at a + b (+ shift rows along the beam): the flat index
        of each sample's lower corner (``idx``, int32), the offset of its nearest corner
        (``near``, float32) and the fractions toward the upper corners per axis, all in ``ws``.
        Returns (idx, an int32 scratch, (fx, fy, fz))."""
        n, e, wc = a.shape[:3]
        shape = (n, e, wc, b.shape[1])
        dmax = self._dmax[pidx]  # (N, 3)
        strides = self._strides[pidx]  # (N, 3) int32
        idx = ws.get("idx", shape, torch.int32)
        idx.copy_(self._offsets[pidx].view(n, 1, 1, 1).expand(shape))
        tmp_i = ws.get("tmp_i", shape, torch.int32)
        near = ws.get("near", shape, torch.float32)  # offset of the nearest corner
        near.zero_()
        fr = []
        for c in range(3):
            v = ws.get(f"v{c}", shape, torch.float32)
            i0 = ws.get("i0", shape, torch.float32)
            torch.add(a[..., c, None], b[:, None, None, :, c], out=v)
            if shift is not None:  # x + 0 * step = x: an unmoved sample keeps its bits
                v.addcmul_(shift, dvr[:, c].float().view(n, 1, 1, 1))
            torch.floor(v, out=i0)
            i0.clamp_(min=0)
            torch.minimum(i0, dmax[:, c].view(n, 1, 1, 1), out=i0)
            f = v.sub_(i0).clamp_(0, 1)  # fraction, in place of v
            fr.append(f)
            tmp_i.copy_(i0)
            if c != 1:
                tmp_i.mul_(strides[:, c].view(n, 1, 1, 1))
            idx.add_(tmp_i)
            # nearest corner: + stride where the fraction >= 0.5
            torch.round(f, out=i0)
            near.add_(i0.mul_(strides[:, c].view(n, 1, 1, 1).float()))
        return idx, tmp_i, tuple(fr)

    def _steps(self, origin, row_step, col_step, pidx, block):
        """(v0, dvr, dvc): the padded voxel coordinates of each slice's first sample (centre
        of its first ``block`` of pixels; (N, E, 3)) and the steps per sample down and across
        ((N, 3) each)."""
        kz, kx = block
        sp = self._spacing[pidx]
        v0 = (
            origin
            + (kz - 1) / 2 * row_step[:, None]
            + (kx - 1) / 2 * col_step[:, None]
            - self._origin[pidx][:, None]
        ) / sp[:, None]
        return v0, kz * row_step / sp, kx * col_step / sp

    def _warp(self, warp, origin, row_step, col_step, pidx) -> torch.Tensor | None:
        """The warp's shifts on its grid (``DepthWarp.stride`` times coarser than the
        samples), (N, E, Wc', Hc') in its rows, from the labels there; None: nothing moves.
        All envs at once, in chunks of ``chunk_samples`` of that grid: the grid is small, and
        a warp is many short passes."""
        pr, (kz, kx), (sd, sl) = self.probe, self.block, warp.stride
        hs, wsub = -(-pr.depth_px // (kz * sd)), -(-pr.width_px // (kx * sl))
        n, e = len(pidx), pr.elevation_px
        v0, dvr, dvc = self._steps(origin, row_step, col_step, pidx, (kz * sd, kx * sl))
        m = torch.arange(hs, device=self.device, dtype=torch.float64)
        cols = torch.arange(wsub, device=self.device, dtype=torch.float64)
        out = torch.empty((n, e, wsub, hs), dtype=torch.float32, device=self.device)
        moved = []

        def run(c: slice, ws: Workspace) -> None:
            a = (v0[c, :, None, :] + cols[None, None, :, None] * dvc[c, None, None, :]).float()
            b = (m[None, :, None] * dvr[c, None, :]).float()
            labels = ws.get("warp_labels", (len(range(n)[c]), e, wsub, hs), torch.uint8)
            self._labels_at(self._nearest_voxels(a, b, pidx[c], ws), ws, labels)
            shift = warp(labels, c, ws)
            moved.append(shift is not None)
            out[c] = 0.0 if shift is None else shift

        step = max(1, self.chunk_samples // (e * hs * wsub))
        self._chunks.run(run, [slice(s, min(n, s + step)) for s in range(0, n, step)])
        return out if any(moved) else None

    @staticmethod
    def _upsample_shift(sub, stride, shape, ws: Workspace) -> torch.Tensor:
        """A warp's shifts ``sub`` (n, E, Wc', Hc', in its rows) at every sample of ``shape``
        (n, E, Wc, Hc), in samples: linear between the warp's samples (block centres, as the
        CT is upsampled), held beyond the last."""
        sd, sl = stride
        if (sd, sl) == (1, 1):
            return sub
        n, e, wsub, hs = sub.shape
        deep = ws.get("warp_deep", (n, e, wsub, hs * sd), torch.float32)
        upsample_linear(sub, 3, sd, deep) if sd > 1 else deep.copy_(sub)
        full = ws.get("warp_full", (n, e, wsub * sl, hs * sd), torch.float32)
        upsample_linear(deep, 2, sl, full) if sl > 1 else full.copy_(deep)
        full = full[:, :, : shape[2], : shape[3]]  # a view: the samples' own columns and rows
        return full if sd == 1 else full.mul_(sd)

    def _nearest_voxels(self, a, b, pidx, ws: Workspace) -> torch.Tensor:
        """Flat indices (int32, in ``ws``) of the voxels nearest to the samples at a + b: the
        labels a warp reads (half-way ties may round the other way than ``_corners``')."""
        n, e, wc = a.shape[:3]
        shape = (n, e, wc, b.shape[1])
        top = self._dmax[pidx] + 1  # (N, 3) the last voxel, the border's
        strides = self._strides[pidx]
        idx = ws.get("nearest", shape, torch.int32)
        idx.copy_(self._offsets[pidx].view(n, 1, 1, 1).expand(shape))
        v = ws.get("v0", shape, torch.float32)
        tmp_i = ws.get("tmp_i", shape, torch.int32)
        zero = torch.zeros((), device=self.device)
        for c in range(3):
            torch.add(a[..., c, None], b[:, None, None, :, c], out=v)
            torch.clamp(v.round_(), zero, top[:, c].view(n, 1, 1, 1), out=v)
            tmp_i.copy_(v)
            if c != 1:
                tmp_i.mul_(strides[:, c].view(n, 1, 1, 1))
            idx.add_(tmp_i)
        return idx

    def _nearest_labels(self, ws: Workspace, lab_c: torch.Tensor) -> None:
        """The labels of the nearest voxels of the samples ``_corners`` just indexed."""
        shape = lab_c.shape
        tmp_i = ws.get("tmp_i", shape, torch.int32)
        tmp_i.copy_(ws.get("near", shape, torch.float32)).add_(ws.get("idx", shape, torch.int32))
        self._labels_at(tmp_i, ws, lab_c)

    def _labels_at(self, voxels: torch.Tensor, ws: Workspace, lab_c: torch.Tensor) -> None:
        """Label ids of flat voxel indices ``voxels`` (int32; overwritten) into ``lab_c``."""
        shape, tmp_i = lab_c.shape, voxels
        if self.labels_packed:
            scratch = (
                ws.get("lab_i0", shape, torch.int32),
                ws.get("lab_i1", shape, torch.int32),
                ws.get("lab_u8", shape, torch.uint8),
            )
            gather_labels(self._nibbles, self._palette, tmp_i, lab_c, scratch)
        else:
            torch.index_select(self._lab, 0, tmp_i.view(-1), out=lab_c.view(-1))

    def _sample(
        self,
        origin: torch.Tensor,
        row_step: torch.Tensor,
        col_step: torch.Tensor,
        pidx: torch.Tensor,
        ct_out: torch.Tensor,
        lab_out: torch.Tensor,
        ws: Workspace,
        moved: tuple[torch.Tensor, tuple[int, int]] | None = None,
    ) -> None:
        n, e, h, w = ct_out.shape
        kz, kx = self.block
        hc, wc = -(-h // kz), -(-w // kx)
        # Samples at the centres of kz x kx pixel blocks, in padded voxel coordinates, laid out
        # (N, E, Wc, Hc): depth runs fastest, along the volume's contiguous y axis. v0 (N, E, 3),
        # dvr and dvc (N, 3) per coarse row and column.
        v0, dvr, dvc = self._steps(origin, row_step, col_step, pidx, self.block)
        m = torch.arange(hc, device=self.device, dtype=torch.float64)
        l_ = torch.arange(wc, device=self.device, dtype=torch.float64)
        # a: per (env, slice, column), b: per (env, row); coordinate = a + b.
        a = (v0[:, :, None, :] + l_[None, None, :, None] * dvc[:, None, None, :]).float()
        b = (m[None, :, None] * dvr[:, None, :]).float()  # (N, Hc, 3)
        shape = (n, e, wc, hc)
        lab_c = ws.get("lab_c", shape, torch.uint8)
        # a warp's shift (tissue compression): sample that many samples deeper along the beam
        shift = None if moved is None else self._upsample_shift(*moved, shape, ws)
        idx, tmp_i, (fx, fy, fz) = self._corners(a, b, shift, dvr, pidx, ws)
        # Labels: nearest voxel.
        self._nearest_labels(ws, lab_c)
        # CT: trilinear from the 8 corners (pairs along the contiguous y axis).
        vol = self._ct
        strides = self._strides[pidx]  # (N, 3) int32
        g16 = ws.get("g16", shape, torch.float16)
        lo = ws.get("lo", shape, torch.float32)
        hi = ws.get("hi", shape, torch.float32)
        acc = [ws.get(f"acc{i}", shape, torch.float32) for i in range(3)]
        sx = strides[:, 0].view(n, 1, 1, 1)
        sz = strides[:, 2].view(n, 1, 1, 1)

        def pair(j: torch.Tensor, dst: torch.Tensor) -> torch.Tensor:
            torch.index_select(vol, 0, j.view(-1), out=g16.view(-1))
            lo.copy_(g16)
            torch.index_select(vol, 0, j.add_(1).view(-1), out=g16.view(-1))
            hi.copy_(g16)
            return torch.lerp(lo, hi, fy, out=dst)

        def along_z(base: torch.Tensor, dst: torch.Tensor) -> torch.Tensor:
            torch.add(base, 0, out=tmp_i)
            p0 = pair(tmp_i, acc[2])
            torch.add(base, sz, out=tmp_i)
            p1 = pair(tmp_i, dst)
            return torch.lerp(p0, p1, fz, out=dst)

        c0 = along_z(idx, acc[0])
        idx.add_(sx)
        c1 = along_z(idx, acc[1])
        ctc = torch.lerp(c0, c1, fx, out=acc[0])  # (N, E, Wc, Hc)
        # Upsample to the pixel grid and transpose to (N, E, H, W).
        ctc_t = ctc.transpose(-1, -2)  # (N, E, Hc, Wc) view
        lab_t = lab_c.transpose(-1, -2)
        exact = hc * kz == h and wc * kx == w
        if (kz, kx) == (1, 1):
            ct_out.copy_(ctc_t)
            lab_out.copy_(lab_t)
            return
        tmp = ws.get("up", (n, e, hc * kz, wc), torch.float32)
        upsample_linear(ctc_t, 2, kz, tmp) if kz > 1 else tmp.copy_(ctc_t)
        full = ct_out if exact else ws.get("full", (n, e, hc * kz, wc * kx), torch.float32)
        upsample_linear(tmp, 3, kx, full) if kx > 1 else full.copy_(tmp)
        labs = lab_out if exact else ws.get("labf", (n, e, hc * kz, wc * kx), torch.uint8)
        labs.view(n, e, hc, kz, wc, kx).copy_(
            lab_t[:, :, :, None, :, None].expand(n, e, hc, kz, wc, kx)
        )
        if not exact:
            ct_out.copy_(full[:, :, :h, :w])
            lab_out.copy_(labs[:, :, :h, :w])
