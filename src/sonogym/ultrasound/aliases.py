"""Former names of the ultrasound simulators and models, each with the version that removes it.

``sonogym``, the reference model's name until the package took it, is ``reference`` now; it is
accepted with a ``DeprecationWarning`` until 0.3.0. Anything that records a simulator (run
configs, the benchmark identity) records the current name (``canonical_name``).
"""

from __future__ import annotations

import warnings

#: Former names: {old: (current name, the version that removes the old one)}.
ALIASES: dict[str, tuple[str, str]] = {"sonogym": ("reference", "0.3.0")}


def is_alias(name: object) -> bool:
    """Whether ``name`` is a simulator's former name."""
    return isinstance(name, str) and name in ALIASES


def alias_note(name: str) -> str:
    """What to tell a user of the former name ``name``."""
    new, removed_in = ALIASES[name]
    return f"simulator {name!r} is now called {new!r}; the old name is removed in {removed_in}"


def canonical_name(name: str, warn: bool = True) -> str:
    """``name``, or the current name of a former one (with a ``DeprecationWarning`` pointing
    at the caller's caller)."""
    if is_alias(name):
        if warn:
            warnings.warn(alias_note(name), DeprecationWarning, stacklevel=3)
        return ALIASES[name][0]
    return name
