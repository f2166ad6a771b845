"""Label volumes at 4 bits per voxel: a 16-entry palette per block of 512 voxels.

A slicer's label buffer is a third of its memory at 1 byte per voxel. Anatomy changes slowly
along the buffer's memory order, so any run of ``BLOCK`` consecutive voxels holds few distinct
labels (at most 12 in the seed-0 phantom and in the shared TotalSegmentator subject at 1 mm,
whose volumes hold 34 and 62 labels). Each voxel then stores its label's index in its block's
palette, two voxels per byte, and a lookup reads the exact label id back: 0.53 bytes per voxel
instead of 1. Where some block holds more than ``PALETTE`` labels, packing reports it
(``pack_labels`` returns None) and the caller keeps plain bytes: nothing is ever approximated.
"""

from __future__ import annotations

import torch

#: Voxels per palette block, in the buffer's memory order (a multiple of 2).
BLOCK = 512
#: Distinct labels a block may hold (4-bit indices).
PALETTE = 16
#: Blocks packed per step while building (bounds the scratch to ~10 MB).
_CHUNK_BLOCKS = 1024


def pack_labels(labels: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor] | None:
    """Pack a flat uint8 label run (CPU, length a multiple of ``BLOCK``).

    Returns:
        (nibbles, palette): nibbles (n / 2,) uint8, voxel 2k's palette index in the low and
        voxel 2k+1's in the high half of byte k; palette (n / BLOCK * PALETTE,) uint8, block b's
        labels at b * PALETTE + index (ascending; unused entries 0). None when a block holds
        more than ``PALETTE`` distinct labels.
    """
    if labels.dtype != torch.uint8 or labels.ndim != 1 or labels.numel() % BLOCK:
        raise ValueError(
            f"pack_labels needs a flat uint8 tensor whose length is a multiple of {BLOCK}, got "
            f"{labels.dtype} of shape {tuple(labels.shape)}"
        )
    blocks = labels.view(-1, BLOCK)
    palette = torch.zeros(blocks.shape[0], PALETTE, dtype=torch.uint8)
    nibbles = torch.empty(labels.numel() // 2, dtype=torch.uint8).view(blocks.shape[0], -1)
    index = torch.empty(min(_CHUNK_BLOCKS, blocks.shape[0]), BLOCK, dtype=torch.uint8)
    for s in range(0, blocks.shape[0], _CHUNK_BLOCKS):
        ordered, order = torch.sort(blocks[s : s + _CHUNK_BLOCKS], dim=1)
        first = torch.ones(ordered.shape, dtype=torch.long)
        first[:, 1:] = ordered[:, 1:] != ordered[:, :-1]
        rank = first.cumsum_(1).sub_(1)  # palette index of each sorted voxel
        if int(rank[:, -1].max()) >= PALETTE:
            return None
        k = ordered.shape[0]
        palette[s : s + k].scatter_(1, rank, ordered)  # equal labels, equal values
        pairs = index[:k].scatter_(1, order, rank.to(torch.uint8)).view(k, -1, 2)
        out = nibbles[s : s + k]
        torch.bitwise_left_shift(pairs[..., 1], 4, out=out).bitwise_or_(pairs[..., 0])
    return nibbles.view(-1), palette.view(-1)


def gather_labels(
    nibbles: torch.Tensor,
    palette: torch.Tensor,
    voxel: torch.Tensor,
    out: torch.Tensor,
    scratch: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
) -> torch.Tensor:
    """Label ids of flat voxel indices ``voxel`` (int32; overwritten) into ``out`` (uint8, same
    shape). ``scratch``: two int32 tensors and one uint8 tensor of that shape."""
    half, shift, byte = scratch
    torch.bitwise_right_shift(voxel, 1, out=half)
    torch.index_select(nibbles, 0, half.view(-1), out=byte.view(-1))
    torch.bitwise_and(voxel, 1, out=shift).mul_(4)  # even voxels in the low half
    half.copy_(byte).bitwise_right_shift_(shift).bitwise_and_(PALETTE - 1)
    # palette entry: block * PALETTE + index (BLOCK and PALETTE are powers of two)
    voxel.bitwise_right_shift_(BLOCK.bit_length() - 1).mul_(PALETTE).add_(half)
    return torch.index_select(palette, 0, voxel.view(-1), out=out.view(-1)).view(out.shape)


def unpack_labels(nibbles: torch.Tensor, palette: torch.Tensor) -> torch.Tensor:
    """The flat uint8 label run that ``pack_labels`` packed into (nibbles, palette)."""
    index = torch.stack([nibbles & (PALETTE - 1), nibbles >> 4], 1).view(-1).long()
    block = torch.arange(index.numel()) // BLOCK
    return palette[block * PALETTE + index]
