"""A spawned child of the team launcher dies with its parent (no orphan processes)."""

from __future__ import annotations

import signal
import sys


def die_with_parent() -> None:
    """Linux: SIGTERM this process when its parent dies (``PR_SET_PDEATHSIG``)."""
    if not sys.platform.startswith("linux"):
        return
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGTERM, 0, 0, 0)  # PR_SET_PDEATHSIG
    except Exception:  # pragma: no cover - best effort
        pass
