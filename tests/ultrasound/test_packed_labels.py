"""Labels at 4 bits per voxel (``sonogym.ultrasound._packed_labels``): exact, or not at all."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest
import torch
from us_synthetic import random_poses

from sonogym.anatomy.totalseg import load_totalsegmentator
from sonogym.ultrasound import ProbeGeometry, Slicer
from sonogym.ultrasound._packed_labels import (
    BLOCK,
    PALETTE,
    gather_labels,
    pack_labels,
    unpack_labels,
)
from sonogym.ultrasound.slicer import PatientCrop

SUBJECT = Path(__file__).resolve().parents[1] / "data" / "totalsegmentator_example"


def _gather_all(nibbles, palette, n):
    voxel = torch.arange(n, dtype=torch.int32)
    out = torch.empty(n, dtype=torch.uint8)
    scratch = (torch.empty(n, dtype=torch.int32), torch.empty(n, dtype=torch.int32),
               torch.empty(n, dtype=torch.uint8))  # fmt: skip
    return gather_labels(nibbles, palette, voxel, out, scratch)


def test_pack_then_gather_returns_every_label_id():
    g = torch.Generator().manual_seed(0)
    blocks = 40
    # each block draws from its own 16 ids anywhere in 0..255 (255 included)
    ids = torch.stack([torch.randperm(256, generator=g)[:PALETTE] for _ in range(blocks)])
    ids[0, 0] = 255
    pick = torch.randint(0, PALETTE, (blocks, BLOCK), generator=g)
    labels = torch.gather(ids, 1, pick).to(torch.uint8).reshape(-1)
    nibbles, palette = pack_labels(labels)
    assert nibbles.numel() == labels.numel() // 2
    assert palette.numel() == blocks * PALETTE
    assert torch.equal(_gather_all(nibbles, palette, labels.numel()), labels)
    # a block's palette: its distinct labels, ascending
    used = torch.unique(labels[:BLOCK])
    assert torch.equal(palette[: used.numel()], used)
    assert torch.equal(unpack_labels(nibbles, palette), labels)


def test_packing_a_chunk_at_a_time_gives_the_same_buffers(monkeypatch):
    """Blocks are packed a chunk at a time (bounded scratch): chunk edges and a short last
    chunk change nothing."""
    import sonogym.ultrasound._packed_labels as packed

    g = torch.Generator().manual_seed(1)
    labels = torch.randint(0, PALETTE, (41 * BLOCK,), generator=g, dtype=torch.uint8)
    labels[5 * BLOCK : 9 * BLOCK] = 7  # single-label blocks across a chunk edge
    whole = pack_labels(labels)
    monkeypatch.setattr(packed, "_CHUNK_BLOCKS", 4)  # 10 chunks of 4 blocks, then 1
    chunked = pack_labels(labels)
    assert all(torch.equal(a, b) for a, b in zip(whole, chunked, strict=True))
    assert torch.equal(unpack_labels(*chunked), labels)


def test_a_block_with_more_than_16_labels_is_not_packed():
    labels = torch.zeros(2 * BLOCK, dtype=torch.uint8)
    labels[BLOCK:] = torch.arange(BLOCK) % (PALETTE + 1) + 1  # 17 ids in the second block
    assert pack_labels(labels) is None
    labels[BLOCK:] = torch.arange(BLOCK) % PALETTE + 1  # 16: the most a block may hold
    assert torch.equal(_gather_all(*pack_labels(labels), labels.numel()), labels)
    with pytest.raises(ValueError, match="multiple of 512"):
        pack_labels(torch.zeros(BLOCK + 1, dtype=torch.uint8))


def _poses_around(patient, n, seed):
    pos, rot = random_poses(n, seed=seed, spread=0.04, max_angle=0.6)
    return pos + torch.tensor(patient.landmarks.vertebra("L4").centre, dtype=pos.dtype), rot


def test_the_real_subject_slices_the_same_packed_and_unpacked():
    subject = load_totalsegmentator(SUBJECT, spacing=0.002)
    probe = ProbeGeometry.linear_2d()
    packed, plain = Slicer(subject, probe), Slicer(subject, probe, packed_labels=False)
    assert packed.labels_packed and not plain.labels_packed
    # volumes (no scratch yet): labels cost ~0.53 instead of 1 byte per voxel
    assert plain.nbytes - packed.nbytes > 0.45 * packed.num_voxels
    pos, rot = _poses_around(subject, 12, seed=4)
    a, b = packed(pos, rot), plain(pos, rot)
    assert torch.equal(a.labels, b.labels) and torch.equal(a.ct, b.ct)
    assert len(torch.unique(a.labels)) > 5  # the images cross several tissues


def test_a_patient_with_a_crowded_block_falls_back_to_bytes_exactly():
    subject = load_totalsegmentator(SUBJECT, spacing=0.002)
    labels = subject.labels.clone()
    x, y, z = (s // 2 for s in labels.shape)
    # 40 ids in a row of memory (y is contiguous): more than 16 in at least one block
    labels[x, y : y + 40, z] = torch.arange(80, 120, dtype=torch.uint8)
    crowded = replace(subject, labels=labels, name="crowded")
    probe = ProbeGeometry.linear_2d()
    sl = Slicer(crowded, probe)
    assert not sl.labels_packed
    pos, rot = _poses_around(subject, 6, seed=5)
    plain = Slicer(crowded, probe, packed_labels=False)
    assert torch.equal(sl(pos, rot).labels, plain(pos, rot).labels)
    assert sl.nbytes == plain.nbytes


def test_a_slicer_from_patient_crops_equals_one_from_the_patients_and_takes_their_buffers():
    """Crops made one patient at a time (what an env over many patients builds from) give the
    same slicer as the patients themselves: same bytes held, bit-identical slices; the slicer
    takes the crops' buffers and refuses a crop that went into another slicer."""
    subject = load_totalsegmentator(SUBJECT, spacing=0.002)
    centre = torch.tensor(subject.landmarks.vertebra("L4").centre).double().numpy()
    half = torch.tensor([0.13, 0.13, 0.12]).double().numpy()  # cuts the scan on every axis
    box = (centre - half, centre + half)
    probe = ProbeGeometry.linear_2d()
    direct = Slicer([subject, subject], probe, crop_boxes=[box, None])
    crops = [PatientCrop.of(subject, box), PatientCrop.of(subject)]
    assert crops[0].span < crops[1].span and crops[0].palette is not None
    assert torch.equal(crops[0].label_bytes()[: crops[0].span], crops[0].label_bytes())
    from_crops = Slicer(crops, probe)
    assert all(c.released for c in crops)
    assert from_crops.nbytes == direct.nbytes and from_crops.names == direct.names
    pos, rot = _poses_around(subject, 8, seed=6)
    for pid in (torch.zeros(8, dtype=torch.long), torch.ones(8, dtype=torch.long)):
        a, b = direct(pos, rot, pid), from_crops(pos, rot, pid)
        assert torch.equal(a.ct, b.ct) and torch.equal(a.labels, b.labels)
    with pytest.raises(ValueError, match="another Slicer"):
        Slicer(crops[:1], probe)
    with pytest.raises(ValueError, match="no crop box"):
        Slicer([PatientCrop.of(subject)], probe, crop_boxes=[box])
