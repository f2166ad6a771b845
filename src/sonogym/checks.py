"""Input checks on tensors that do not stop the device.

Reading a tensor on the host (``bool(t.any())``, ``int(t.max())``, ``t.tolist()``, boolean
masks) makes the CPU wait for a CUDA device: a handful per env step costs more than the step's
kernels. ``expect_all`` checks a condition without that wait:

* on CPU (no device to wait for) it raises ``ValueError`` at once, with the full message;
* on CUDA it queues ``torch._assert_async``: a false condition stops the process at the next
  host read with a device-side assertion (the message is printed, the CUDA context is lost).
  ``SONOGYM_SYNC_CHECKS=1`` makes CUDA checks host-side too, with the CPU's clear errors, at the
  price of one host read per check (use it to debug bad inputs).

``tests/envs/test_host_syncs.py`` counts the host reads left in each task's step.
"""

from __future__ import annotations

import os
from collections.abc import Callable

import torch

__all__ = ["expect_all", "sync_checks"]


def sync_checks(device: torch.device) -> bool:
    """Whether checks on ``device`` read the condition on the host (CPU, or the env var)."""
    return device.type == "cpu" or os.environ.get("SONOGYM_SYNC_CHECKS", "") not in ("", "0")


def expect_all(cond: torch.Tensor, message: str | Callable[[], str]) -> None:
    """Raise ``ValueError(message)`` unless every element of the bool tensor ``cond`` is true.

    ``message`` may be a callable, called only on failure (so details such as which envs are
    bad cost nothing when all is well)."""
    if sync_checks(cond.device):
        if not bool(cond.all()):
            raise ValueError(message() if callable(message) else message)
        return
    static = message if isinstance(message, str) else "input check failed"
    torch._assert_async(cond.all(), f"{static} (SONOGYM_SYNC_CHECKS=1 for a host-side check)")
