"""Reusable scratch buffers for the hot paths.

Fresh multi-megabyte tensors are expensive on CPU (every new block is page-faulted in; on the
2-core VMs this project targets that costs more than the arithmetic). The slicer and the
simulator therefore keep their temporaries in named buffers that grow to the largest size seen
and are reused by every later call. Not thread-safe: one workspace per slicer / simulator.
"""

from __future__ import annotations

import math

import torch


class Workspace:
    """Named scratch buffers, reused across calls."""

    def __init__(self, device: torch.device) -> None:
        self.device = device
        self._bufs: dict[str, torch.Tensor] = {}

    def get(self, name: str, shape: tuple[int, ...], dtype: torch.dtype) -> torch.Tensor:
        """A contiguous tensor of ``shape`` and ``dtype`` (uninitialised), the same storage for the
        same name on every call."""
        n = math.prod(shape)
        buf = self._bufs.get(name)
        if buf is None or buf.dtype != dtype or buf.numel() < n:
            buf = torch.empty(n, dtype=dtype, device=self.device)
            self._bufs[name] = buf
        return buf[:n].view(shape)

    @property
    def nbytes(self) -> int:
        return sum(b.numel() * b.element_size() for b in self._bufs.values())

    def clear(self) -> None:
        self._bufs.clear()
