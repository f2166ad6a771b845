"""The learned-simulator nets shipped with the package, and resolving a net spec to files.

``weights/net0.pt`` ... ``net4.pt`` are five generators trained by
``sonogym.learned_training.recipe`` with seeds 0-4 (docs/learned_model_card.md). A net spec
is a tuple whose items are ints (shipped nets, by index) or paths (a user's ``generator.pt``
from ``sonogym lb-train``).
"""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from functools import cache
from pathlib import Path

WEIGHTS_DIR = Path(__file__).parent / "weights"
NUM_SHIPPED = 5


def shipped_weights(index: int) -> Path:
    """Path of shipped net ``index`` (0-4)."""
    if isinstance(index, bool) or not isinstance(index, int):
        raise TypeError(f"a shipped net index must be an int, got {index!r}")
    if not 0 <= index < NUM_SHIPPED:
        raise ValueError(
            f"unknown shipped net {index}: the package ships nets 0-{NUM_SHIPPED - 1}; pass a "
            "path to a generator.pt (sonogym lb-train) for other weights"
        )
    path = WEIGHTS_DIR / f"net{index}.pt"
    if not path.is_file():
        raise FileNotFoundError(
            f"shipped net {index} is missing ({path}); reinstall sonogym, or rebuild the weights "
            "with scripts/train_learned_nets.sh"
        )
    return path


def resolve_nets(spec: int | str | Path | Sequence[int | str | Path]) -> list[Path]:
    """A net spec (int index, path, or a sequence of them) -> checkpoint paths."""
    items = [spec] if isinstance(spec, (int, str, Path)) else list(spec)
    if not items:
        raise ValueError("learned_nets is empty: give at least one shipped index or weights path")
    out = []
    for it in items:
        if isinstance(it, (str, Path)):
            p = Path(it).expanduser()
            if not p.is_file():
                raise FileNotFoundError(
                    f"learned net weights {str(p)!r} not found: give the path of a generator.pt "
                    "written by sonogym lb-train, or an int 0-4 for a shipped net"
                )
            out.append(p)
        else:
            out.append(shipped_weights(it))
    return out


def file_digest(path: str | Path) -> str:
    """First 16 hex digits of a file's SHA-256: how identities name a net's weights."""
    return _file_digest(str(Path(path).resolve()))


@cache
def _file_digest(path: str) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()[:16]


def net_digests(nets) -> dict[str, str]:
    """``{name: digest}`` of the learned nets a ``learned_nets`` spec names: shipped nets as
    ``net<i>``, a user's file by its path."""
    items = [nets] if isinstance(nets, int | str | Path) else list(nets)
    out = {}
    for item, path in zip(items, resolve_nets(items), strict=True):
        name = f"net{item}" if isinstance(item, int) else str(path)
        out[name] = file_digest(path)
    return out
