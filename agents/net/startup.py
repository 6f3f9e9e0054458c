"""Starting a team's processes (:mod:`agents.net.launcher`): the fork server the children
are forked from, the Zenoh links between the processes and the agents each agent process
hosts."""

from __future__ import annotations

import atexit
import contextlib
import multiprocessing
import os
import sys
import types
from collections.abc import Iterable, Iterator, Sequence
from typing import TYPE_CHECKING, Any

from estimation.errors import ScenarioError

if TYPE_CHECKING:
    from .slices import AgentSlice

#: what the fork server imports once for every child it forks (an agent needs nothing else
#: but its estimator's module); the plant and monitor import the rest of theirs after the fork
PRELOAD = ["numpy", "numpy.random", "msgpack", "zenoh", "uvloop", "transport.codec", "transport.keys", "transport.zenoh_bus",
           "transport.zenoh_session", "transport.channel", "transport.byzantine", "agents.node", "agents.net.child",
           "agents.net.agent", "agents.net.plant", "agents.net.slices",
           # the built-in estimators (numpy only at import; an agent unpickles one of them)
           "estimation.lfre", "estimation.lee_kim_shim", "estimation.ugrinovskii", "estimation.mao_tabuada",
           "estimation.median_bank", "estimation.distributed_median", "estimation.inverters"]


def child_env() -> None:
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")  # tiny matrices: one BLAS thread per process (inherited by the children)


def prestart() -> None:
    """Start the fork server now (it preloads :data:`PRELOAD` while the caller builds the
    experiment); :func:`launch` uses it. Does nothing with the ``spawn`` start method. The
    fork server and its resource tracker are stopped when this process exits
    (:func:`stop_helpers`)."""
    child_env()
    from transport.event_loop import loop_factory

    loop_factory()  # a bad RSE_EVENT_LOOP is one error here, not one per child
    ctx = context()
    if ctx.get_start_method() == "forkserver":
        from multiprocessing import forkserver

        with bare_main():
            forkserver.ensure_running()
        atexit.unregister(stop_helpers)
        atexit.register(stop_helpers)


def stop_helpers() -> None:
    """Stop the fork server and the resource tracker this process started and wait for
    them. Left alone they end only once they notice this process is gone (the end of a pipe),
    which on a loaded machine came more than 0.5 s after a command had exited on Ctrl-C:
    processes left behind for that while. ``_stop`` is what Python's own tests call (3.11
    has no public way to stop them)."""
    from multiprocessing import forkserver, resource_tracker

    for helper in (forkserver._forkserver, resource_tracker._resource_tracker):
        with contextlib.suppress(Exception):
            helper._stop()  # type: ignore[union-attr]  # private (no public stop in 3.11); closes its pipe, then waits for it


def context() -> Any:
    """The start method of the children: a fork server that preloaded :data:`PRELOAD`
    (each child is a fork of it: no interpreter start-up nor numpy/Zenoh import per child;
    Zenoh opens its runtime only in the child's session), else ``spawn``."""
    if os.environ.get("RSE_START_METHOD", "forkserver") == "forkserver" and \
            "forkserver" in multiprocessing.get_all_start_methods():
        ctx = multiprocessing.get_context("forkserver")
        ctx.set_forkserver_preload(PRELOAD)
        return ctx
    return multiprocessing.get_context("spawn")


PEER_RETRY_MS = 50  # a peer retries a connect endpoint that is not listening yet this soon


def peer_links(slices: Sequence[AgentSlice], host: dict[int, str] | None = None) -> dict[str, set[str]]:
    """Process name -> the processes it exchanges messages with: the plant and the monitor
    with everyone; an agent with its in- and out-neighbours; an omniscient adversary also
    with the other in-neighbours of its out-neighbours (whose messages its view reads).
    ``host``: agent id -> the name of its process (default ``agent I``)."""
    host = host or {s.agent_id: f"agent {s.agent_id}" for s in slices}
    agents = set(host.values())
    links: dict[str, set[str]] = {"plant": {"monitor", *agents}, "monitor": {"plant", *agents}}
    for s in slices:
        me = host[s.agent_id]
        near = set(s.in_ids) | set(s.out_ids)
        if s.view is not None:
            near |= {j for v in s.view.before.values() for j in v} | set(s.view.needed)
        links.setdefault(me, {"plant", "monitor"}).update(host[j] for j in near if host[j] != me)
    for nm, others in list(links.items()):  # symmetric
        for o in others:
            links.setdefault(o, set()).add(nm)
    return links


def agent_groups(agent_ids: Iterable[int], per_process: int) -> list[tuple[int, ...]]:
    """The agents of each agent process: ``per_process`` consecutive ids each (the last
    group may be smaller)."""
    if per_process < 1:
        raise ScenarioError(f"agents per process must be >= 1, got {per_process}")
    ids = list(agent_ids)
    return [tuple(ids[i:i + per_process]) for i in range(0, len(ids), per_process)]


@contextlib.contextmanager
def bare_main() -> Iterator[None]:
    """While a child is spawned, hide the launching program's ``__main__`` (the ``rse``
    script, a notebook, a test runner): ``spawn`` would import it again in every child
    (with the CLI's libraries), and a child needs only :func:`child_entry`'s module."""
    real = sys.modules.get("__main__")
    sys.modules["__main__"] = types.ModuleType("__main__")
    try:
        yield
    finally:
        if real is not None:
            sys.modules["__main__"] = real
