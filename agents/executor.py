"""One executor for everything that fans simulator runs out: sweeps, boundary searches,
red-team searches (DESIGN.md, "Many runs").

::

    with open_executor(jobs=2) as ex:                 # or cluster="tcp://HOST:8786"
        for index, result in ex.map(run_one, [(a,), (b,), ...]):
            ...                                      # results as they complete

A task is a module-level function and picklable arguments (a frozen scenario and its
overrides, never a live object or a path the worker may not have); results come back in
completion order with the index of their task, so a caller writes each as it arrives
(on its own side: a task writes no file) and stays resumable. Leaving the ``with`` block
cancels what has not started and shuts the workers down; leaving it by an exception or
Ctrl-C / SIGTERM also terminates the local tasks that are running (within a second, no
orphan).

Two implementations: :class:`LocalExecutor`, a ``spawn`` process pool on this machine
(the default), and :class:`DaskExecutor`, a Dask distributed cluster (``Client.submit``
and ``distributed.as_completed``; needs the ``cluster`` extra). On a Dask cluster a task
whose worker dies is run again on another worker by the scheduler; each task still
yields exactly once here, so a caller that writes on arrival writes every run once.
The process pool stays the local default: on this project's sweeps a ``LocalCluster`` of
the same size was not measurably faster, costs 5 to 8 CPU seconds more per sweep and
took 21 s to start and 5 s to close on a loaded machine, against 1.4 s and 0.5 s for the
pool (docs/sweeps.md, "Throughput").
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from multiprocessing import get_context
from typing import Any, Protocol

__all__ = ["Executor", "LocalExecutor", "DaskExecutor", "open_executor"]


class Executor(Protocol):
    """Runs ``fn(*args)`` for each task, in parallel; yields ``(task index, result)`` as
    tasks complete. An exception raised by a task is re-raised by the iterator."""

    def map(self, fn: Callable[..., Any], tasks: Sequence[tuple[Any, ...]]) -> Iterator[tuple[int, Any]]: ...

    def close(self) -> None: ...

    def __enter__(self) -> Executor: ...

    def __exit__(self, *exc: Any) -> None: ...


class LocalExecutor:
    """Worker processes on this machine (``spawn``: a worker imports only what its task
    needs; the parent's BLAS settings are inherited through the environment)."""

    def __init__(self, jobs: int) -> None:
        self.jobs = max(1, int(jobs))
        self._pool: ProcessPoolExecutor | None = None

    def __enter__(self) -> LocalExecutor:
        return self

    def __exit__(self, exc_type: Any, *exc: Any) -> None:
        self.close(now=exc_type is not None)

    def _ensure(self) -> ProcessPoolExecutor:
        if self._pool is None:
            self._pool = ProcessPoolExecutor(max_workers=self.jobs, mp_context=get_context("spawn"),
                                             initializer=_ignore_sigint)
        return self._pool

    def map(self, fn: Callable[..., Any], tasks: Sequence[tuple[Any, ...]]) -> Iterator[tuple[int, Any]]:
        if not tasks:
            return
        pool = self._ensure()
        futs: dict[Future, int] = {pool.submit(fn, *args): i for i, args in enumerate(tasks)}
        pending = set(futs)
        interrupted = True
        try:
            while pending:
                done, pending = wait(pending, return_when=FIRST_COMPLETED)
                for fut in done:
                    yield futs[fut], fut.result()
            interrupted = False
        finally:
            if interrupted:
                self.close(now=True)

    def close(self, *, now: bool = False) -> None:
        """Shut the workers down: after the running tasks finish, or (``now``: the caller
        is leaving on an exception or a signal) at once, terminating the running tasks
        (a task writes its result last, so an interrupted one is simply not done)."""
        if self._pool is None:
            return
        pool, self._pool = self._pool, None
        if not now:
            pool.shutdown(wait=True, cancel_futures=True)
            return
        procs = list((getattr(pool, "_processes", None) or {}).values())
        for proc in procs:
            proc.kill()  # a worker holds nothing to close: its task's files are written atomically
        for proc in procs:  # joined: no orphan, no zombie
            proc.join()
        # the pool sees its workers gone and fails every future left (cancelling them here
        # as well races with that in CPython 3.11: an InvalidStateError, then a hang); its
        # management thread is not waited for either (it could wait on a dead worker's
        # queue): the workers are gone, and the command exits right after this
        pool.shutdown(wait=False, cancel_futures=False)


def _ignore_sigint() -> None:
    """Workers leave Ctrl-C to the parent, which stops them (a terminal sends SIGINT to
    the whole process group)."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)


class DaskExecutor:
    """Tasks on a Dask distributed cluster: the scheduler at ``address``
    (``tcp://HOST:8786``), or, with ``address="local"``, a ``LocalCluster`` of ``jobs``
    single-threaded worker processes started here.

    The client connects when the executor is entered; an address that does not answer
    within ``timeout`` seconds is a :class:`~estimation.errors.ScenarioError` naming it.
    Workers need the installed package only: a task is pickled by reference to its
    module-level function, with its arguments by value.
    """

    def __init__(self, address: str, jobs: int = 1, *, timeout: float = 10.0) -> None:
        self.address = address
        self.jobs = max(1, int(jobs))
        self.timeout = timeout
        self._client: Any = None
        self._cluster: Any = None

    def __enter__(self) -> DaskExecutor:
        self._ensure()
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def _ensure(self) -> Any:
        if self._client is not None:
            return self._client
        from estimation.errors import ScenarioError

        try:
            import distributed
        except ImportError:
            raise ScenarioError("Dask is not installed: pip install 'resilient-state-estimation[cluster]'",
                                source="--cluster") from None
        if self.address == "local":
            import logging

            self._cluster = distributed.LocalCluster(n_workers=self.jobs, threads_per_worker=1, processes=True,
                                                     dashboard_address=None, silence_logs=logging.ERROR)
            self._client = distributed.Client(self._cluster, set_as_default=False)
            return self._client
        if "://" not in self.address:
            raise ScenarioError(f"expected a scheduler address such as tcp://HOST:8786, got {self.address!r}",
                                source="--cluster")
        try:
            self._client = distributed.Client(self.address, timeout=self.timeout, set_as_default=False)
        except (OSError, TimeoutError, ValueError) as exc:
            raise ScenarioError(f"no Dask scheduler answers at {self.address} ({type(exc).__name__})",
                                source="--cluster") from None
        return self._client

    def workers(self) -> int:
        """The number of workers connected now."""
        return len(self._ensure().scheduler_info().get("workers", {}))

    def map(self, fn: Callable[..., Any], tasks: Sequence[tuple[Any, ...]]) -> Iterator[tuple[int, Any]]:
        if not tasks:
            return
        import uuid

        from distributed import KilledWorker, as_completed

        from estimation.errors import RSEError

        client = self._ensure()
        tag = uuid.uuid4().hex[:8]
        name = getattr(fn, "__name__", "task")
        futs = {client.submit(fn, *args, key=f"{name}-{tag}-{i}", pure=False): i for i, args in enumerate(tasks)}
        pending = set(futs)
        try:
            for fut in as_completed(list(futs), loop=client.loop):
                pending.discard(fut)
                try:
                    result = fut.result()
                except KilledWorker:  # the scheduler gave up after allowed-failures worker deaths
                    raise RSEError(f"task {futs[fut]} of {len(futs)} lost: every worker that ran it died "
                                   "(distributed.scheduler.allowed-failures); finished runs are kept") from None
                yield futs[fut], result
        finally:
            if pending:
                client.cancel(list(pending), force=True)

    def close(self) -> None:
        client, cluster = self._client, self._cluster
        self._client = self._cluster = None
        # a slow shutdown (a loaded machine) is not an error of the sweep: its results are written
        if client is not None:
            with contextlib.suppress(TimeoutError, OSError):
                client.close(timeout=2)
        if cluster is not None:
            with contextlib.suppress(TimeoutError, OSError):
                cluster.close(timeout=10)


def open_executor(jobs: int, cluster: str | None = None) -> Executor:
    """The executor for ``jobs`` local worker processes, or for the Dask cluster whose
    scheduler is at ``cluster`` (``tcp://HOST:8786``; ``"local"``: a Dask ``LocalCluster``
    of ``jobs`` processes on this machine)."""
    if cluster is not None:
        return DaskExecutor(cluster, jobs)
    return LocalExecutor(jobs)


def run_all(fn: Callable[..., Any], tasks: Iterable[tuple[Any, ...]], *, jobs: int,
            cluster: str | None = None) -> Iterator[tuple[int, Any]]:
    """``open_executor(jobs, cluster).map(fn, tasks)`` in one call (the executor closes when
    the iteration ends)."""
    with open_executor(jobs, cluster) as ex:
        yield from ex.map(fn, list(tasks))
