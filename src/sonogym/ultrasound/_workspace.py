"""Reusable scratch buffers for the hot paths, and the chunk loop that spreads them over threads.

Fresh multi-megabyte tensors are expensive on CPU (every new block is page-faulted in; on the
2-core VMs this project targets that costs more than the arithmetic). The slicer and the
simulator therefore keep their temporaries in named buffers that grow to the largest size seen
and are reused by every later call. A ``Workspace`` is not thread-safe: ``ChunkRunner`` gives
each of its workers its own.

Why threads over chunks: on CPU the slicer and the simulator work in cache-sized chunks of
envs, each a few dozen small gathers and elementwise passes. torch splits each pass over its
intra-op threads, but the gathers (``index_select``) stay on one thread and the passes are
too short to scale, so 2 threads sped 100 images up by only 1.0x (slice) and 1.4x (simulate).
Whole chunks on separate threads (torch releases the GIL inside every op) scale ~1.9x, with
the same bits, since a chunk's result does not depend on which thread computed it.
"""

from __future__ import annotations

import math
import os
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor, wait
from typing import TypeVar

import torch

C = TypeVar("C")


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


#: Elements below which ATen runs an elementwise op on one thread (``at::internal::GRAIN_SIZE``).
_GRAIN = 32768
#: A multiple of what ATen's vectorised loop takes per step (two vectors; 32 floats with AVX-512).
_VECTOR_STEP = 64


def exp2_(t: torch.Tensor) -> torch.Tensor:
    """``t.exp2_()`` for a contiguous CPU tensor, with the same bits for any batch size and any
    number of threads.

    ATen computes a range's last ``n mod 2 * vector width`` elements with a scalar exp2 that
    differs from the vectorised one by an ulp, so where a range ends (the batch size, the split
    over intra-op threads) changed the result. Here every element takes the vectorised path:
    blocks of ``_GRAIN`` elements (never split, no remainder) and a padded copy of the rest.
    """
    flat = t.view(-1)
    if t.device.type != "cpu":
        return t.exp2_()
    n = flat.numel()
    body = n - n % _VECTOR_STEP
    for block in flat[:body].split(_GRAIN):
        block.exp2_()
    if body < n:
        rest = torch.zeros(_VECTOR_STEP, dtype=t.dtype)
        rest[: n - body] = flat[body:]
        flat[body:] = rest.exp2_()[: n - body]
    return t


#: Most threads one call fans out to: each holds its own scratch (the simulator's is ~40 MB),
#: and two cores were what we could measure (benchmarks/README.md, "Ultrasound").
MAX_CHUNK_WORKERS = 8

_pool: ThreadPoolExecutor | None = None
_pool_lock = threading.Lock()
_local = threading.local()  # .worker is True inside a chunk worker


def _forget_pool_after_fork() -> None:
    # a forked child has none of the parent's threads: a pool inherited from the parent would
    # queue work that never runs, so the child starts its own
    global _pool, _pool_lock
    _pool = None
    _pool_lock = threading.Lock()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_pool_after_fork)


def _helpers() -> ThreadPoolExecutor:
    """The process-wide pool of helper threads (started on demand, at most
    ``MAX_CHUNK_WORKERS - 1``; the caller's thread is the other worker)."""
    global _pool
    with _pool_lock:
        if _pool is None:
            _pool = ThreadPoolExecutor(MAX_CHUNK_WORKERS - 1, "sonogym-chunks")
        return _pool


class ChunkRunner:
    """Runs ``fn(chunk, workspace)`` over a list of independent chunks.

    On CPU with T = min(``torch.get_num_threads()``, ``MAX_CHUNK_WORKERS``, chunks) > 1, the
    chunks are spread over T threads (the caller's and T - 1 helper threads; chunk i on thread
    i mod T), each with its own ``Workspace``; otherwise, and on other devices, they run in
    order on the caller's thread with one workspace. Chunks must write disjoint outputs and
    read only shared inputs. A call made from inside a chunk runs serially (no nested fan-out,
    so no pool deadlock). Like a ``Workspace``, one runner serves one caller at a time.
    """

    def __init__(self, device: torch.device) -> None:
        self.device = torch.device(device)
        self.workspaces = [Workspace(self.device)]

    @property
    def nbytes(self) -> int:
        return sum(ws.nbytes for ws in self.workspaces)

    def workers(self, chunks: int) -> int:
        """Threads a call with ``chunks`` chunks uses."""
        if self.device.type != "cpu" or getattr(_local, "worker", False):
            return 1
        return max(1, min(torch.get_num_threads(), MAX_CHUNK_WORKERS, chunks))

    def run(self, fn: Callable[[C, Workspace], None], chunks: Sequence[C]) -> None:
        t = self.workers(len(chunks))
        while len(self.workspaces) < t:
            self.workspaces.append(Workspace(self.device))
        if t == 1:
            for chunk in chunks:
                fn(chunk, self.workspaces[0])
            return

        def share(w: int) -> None:
            _local.worker = True
            try:
                for chunk in chunks[w::t]:
                    fn(chunk, self.workspaces[w])
            finally:
                _local.worker = False

        futures = [_helpers().submit(share, w) for w in range(1, t)]
        try:
            share(0)
        finally:
            wait(futures)  # all of them, before raising: they write into the caller's out
        for f in futures:
            f.result()
