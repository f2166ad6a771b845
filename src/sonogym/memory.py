"""How much memory the machine has free (for loaders and caches that size themselves)."""

from __future__ import annotations

import os


def available_memory() -> int | None:
    """Bytes of memory available now (Linux MemAvailable; else physical memory; None if the
    platform says neither)."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return None
