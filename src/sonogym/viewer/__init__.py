"""``sonogym view``: a 3-D view of an env, a run's saved episodes or a recorded dataset in Rerun.

Above evaluation (it plays runs' policies and reads their episode logs and datasets), below the
CLI. Rerun (``rerun-sdk``) is the optional ``viewer`` extra: ``require_rerun`` says how to get
it; the modules that log (``draw``, ``env_view``, ``replay``, ``session``) import it at the top
and are imported only after that check. ``geometry`` is plain NumPy.
"""

from __future__ import annotations

INSTALL_HINT = (
    "pip install 'sonogym[viewer]' (Python >= 3.11), or `make install`, which installs it"
)


def require_rerun():
    """The ``rerun`` module; ``ImportError`` naming how to install it when it is missing."""
    try:
        import rerun
    except ImportError as e:
        raise ImportError(
            f"sonogym view needs the Rerun SDK (rerun-sdk), which is not installed: {INSTALL_HINT}"
        ) from e
    return rerun
