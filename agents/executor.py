"""One executor for everything that fans simulator runs out: sweeps, boundary searches,
red-team searches (DESIGN.md, "Many runs").

::

    with open_executor(jobs=2) as ex:                 # or cluster="tcp://HOST:8786"
        for index, result in ex.map(run_one, [(a,), (b,), ...]):
            ...                                      # results as they complete

A task is a module-level function and picklable arguments (a frozen scenario and its
overrides, never a live object); results come back in completion order with the index
of their task, so a caller writes each as it arrives and stays resumable. Leaving the
``with`` block (also by an exception or Ctrl-C) cancels what has not started and shuts
the workers down.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from multiprocessing import get_context
from typing import Any, Protocol

__all__ = ["Executor", "LocalExecutor", "open_executor"]


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

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def _ensure(self) -> ProcessPoolExecutor:
        if self._pool is None:
            self._pool = ProcessPoolExecutor(max_workers=self.jobs, mp_context=get_context("spawn"))
        return self._pool

    def map(self, fn: Callable[..., Any], tasks: Sequence[tuple[Any, ...]]) -> Iterator[tuple[int, Any]]:
        if not tasks:
            return
        pool = self._ensure()
        futs: dict[Future, int] = {pool.submit(fn, *args): i for i, args in enumerate(tasks)}
        pending = set(futs)
        try:
            while pending:
                done, pending = wait(pending, return_when=FIRST_COMPLETED)
                for fut in done:
                    yield futs[fut], fut.result()
        finally:
            for fut in pending:
                fut.cancel()

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None


def open_executor(jobs: int, cluster: str | None = None) -> Executor:
    """The executor for ``jobs`` local worker processes, or for the Dask cluster whose
    scheduler is at ``cluster`` (``tcp://HOST:8786``)."""
    if cluster is not None:
        raise NotImplementedError("Dask clusters are not supported yet")
    return LocalExecutor(jobs)


def run_all(fn: Callable[..., Any], tasks: Iterable[tuple[Any, ...]], *, jobs: int,
            cluster: str | None = None) -> Iterator[tuple[int, Any]]:
    """``open_executor(jobs, cluster).map(fn, tasks)`` in one call (the executor closes when
    the iteration ends)."""
    with open_executor(jobs, cluster) as ex:
        yield from ex.map(fn, list(tasks))
