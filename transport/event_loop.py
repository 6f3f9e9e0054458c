"""The event loop the networked processes run on.

Every process of ``rse run`` (and of ``rse plant`` / ``rse agent`` / ``rse monitor``, and
the bare Zenoh skeletons of ``rse bench run``) runs its role with :func:`run`: on
`uvloop <https://github.com/MagicStack/uvloop>`_ (libuv) where it is installed (a
dependency of the package on Linux and macOS), else on asyncio's own loop. The roles use
only asyncio's API (``call_soon_threadsafe`` from Zenoh's threads, timers, signal
handlers); both loops run them alike.

Why: a lockstep round of ``mitra_cells.toml`` wakes each agent's loop three to four times
(its measurement and its in-neighbours' reports, handed over by :mod:`transport.bridge`),
and asyncio's wake-up (a byte through its self-pipe, ``epoll``, two ``recv`` calls and an
exception per wake-up) was a visible share of an agent's main thread. Whole ``rse run``
commands on uvloop against asyncio, paired runs: ``mitra_cells.toml`` (1000 rounds) 0.92
of the CPU and of the wall time, ``lee_kim_shim.toml --set run.dt=0.01`` 0.89 and 0.90
(docs/networked-runtime.md has the figures).

``RSE_EVENT_LOOP=asyncio`` picks asyncio's loop (``uvloop`` asks for uvloop and fails when
it is not installed). The launcher's children inherit the variable.
"""

from __future__ import annotations

import asyncio
import os
from collections.abc import Callable, Coroutine
from typing import Any, TypeVar

from estimation.errors import RSEError

__all__ = ["loop_factory", "loop_name", "run"]

T = TypeVar("T")

ENV = "RSE_EVENT_LOOP"
CHOICES = ("uvloop", "asyncio")


def _choice() -> str | None:
    value = os.environ.get(ENV, "").strip().lower()
    if value and value not in CHOICES:
        raise RSEError(f"{ENV}={os.environ[ENV]!r}: expected one of {', '.join(CHOICES)}")
    return value or None


def loop_factory() -> Callable[[], asyncio.AbstractEventLoop] | None:
    """The factory of the loop :func:`run` uses: ``uvloop.new_event_loop``, or None for
    asyncio's own (``RSE_EVENT_LOOP=asyncio``, or uvloop not installed)."""
    choice = _choice()
    if choice == "asyncio":
        return None
    try:
        import uvloop
    except ImportError:
        if choice == "uvloop":
            raise RSEError(f"{ENV}=uvloop but uvloop is not installed (pip install uvloop)") from None
        return None
    return uvloop.new_event_loop


def loop_name() -> str:
    """``"uvloop 0.23.0"`` or ``"asyncio"``: what :func:`run` runs on here."""
    if loop_factory() is None:
        return "asyncio"
    import uvloop

    return f"uvloop {uvloop.__version__}"


def run(coro: Coroutine[Any, Any, T]) -> T:
    """``asyncio.run(coro)`` on the loop of :func:`loop_factory`."""
    try:
        factory = loop_factory()
    except BaseException:
        coro.close()  # never awaited: no warning about it
        raise
    with asyncio.Runner(loop_factory=factory) as runner:
        return runner.run(coro)
