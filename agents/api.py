"""The public Python API of ``rse``: the one path the CLI, the sweeps and the benchmarks use.

::

    import rse                                    # the facade package re-exports this module
    exp = rse.load("scenarios/lee_kim_shim.toml", set={"run.dt": 0.01}, seed=3)
    run = rse.simulate(exp)                       # in-process, lockstep, deterministic
    run.metrics()                                 # pandas DataFrame: the columns of metrics.parquet
    run.summary(); run.expectations(); run.save("runs/x")
    team = rse.run_team(exp, out="runs/y")        # the same scenario as processes over Zenoh
    rse.replay("runs/y", set={"estimator.variant": "linear"})  # its deliveries, another estimator
    rse.check(exp)                                # the paper's conditions, as data
    rse.sweep("scenarios/mitra_cells.toml", {"network.channel.drop_p": [0.1, 0.5]}, seeds=3)
    rse.sweep(..., cluster="tcp://HOST:8786")     # the same runs on a Dask cluster
    rse.boundary("scenarios/mitra_cells.toml", "network.channel.drop_p", (0, 0.95),
                 metric="relative_error_2", threshold=1e-6, seeds=20)   # probabilistic bisection

Everything here raises the runtime's own exceptions (:mod:`estimation.errors`): a bad
scenario or override is a :class:`~estimation.errors.ScenarioError` naming the file and key.

The runtime's linear algebra is many small products, where a multi-threaded BLAS only adds
contention: :func:`pin_blas_threads` (called by ``rse``'s ``main()``) sets the usual
variables to one thread; call it before numpy is imported (for example at the top of a
script) to get the same behaviour from Python.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from .runs import RunResult, _override_strings, check, deferred_signals, ended_by, load, load_experiment, open_run, pin_blas_threads, simulate
from .threat import beyond_threat_model

if TYPE_CHECKING:  # pragma: no cover
    import pandas as pd

    from scenarios.build import Experiment

__all__ = [
    "load",
    "simulate",
    "run_team",
    "check",
    "sweep",
    "boundary",
    "beyond_threat_model",
    "open_run",
    "RunResult",
    "pin_blas_threads",
    "load_experiment",
    "deferred_signals",
    "ended_by",
    "replay",
    "chaos",
]


def run_team(exp: Experiment, *, out: str | Path | None = None, mode: str = "lockstep", rate: float | None = None,
             deadline: float = 1.0, startup_timeout: float = 60.0, warmup: float = 3.0, router: bool = False,
             connect: Iterable[str] = (), secure: str | Path | None = None, run_id: str | None = None,
             progress: bool = False, save_estimates: bool = False, agents_per_process: int = 1,
             dashboard: Any = None, on_urls: Callable[[dict[str, str]], None] | None = None,
             while_serving: Callable[[dict[str, Any] | None], None] | None = None,
             say: Callable[[str], None] | None = None, deliveries: bool = True,
             sign: str | Path | None = None) -> RunResult:
    """Run ``exp`` as a team of processes over Zenoh on this machine (``rse run`` is a shell
    over this function): plant, monitor and one process per agent (``agents_per_process``:
    that many agents share a process). Lockstep results equal :func:`simulate`'s.

    ``connect``: routers or peers to join (``tcp/HOST:PORT``), ``router``: start a router for
    the team, ``secure``: a directory of ``rse certs`` (mutual TLS; secure peer-to-peer
    unless a router is used). Hooks: ``dashboard`` the monitor's
    :class:`~agents.dashboard.DashboardOptions`, ``on_urls(urls)`` once it serves them,
    ``while_serving(summary)`` after the run while a served viewer is still up, ``say(line)``
    for the launcher's one-line notes (default: silent). ``deliveries``: every agent records
    what it held at each step (``rse replay``; off only to measure what the record costs).
    ``sign``: a directory of ``rse certs`` signing keys: every estimate is signed and an
    equivocating agent is convicted (``summary["evidence"]``, ``RUN_DIR/evidence.jsonl``).

    Returns when the team has finished (``result.leaves`` lists the members that left
    during the run); raises :class:`~estimation.errors.RSEError` naming the failed process
    otherwise, ``KeyboardInterrupt`` when the run was interrupted.
    """
    from agents.net.exits import EXIT_INTERRUPTED
    from estimation.errors import RSEError, ScenarioError

    from .net.config import RunConfig
    from .net.launcher import Hooks, launch
    from .rundir import default_run_dir

    try:
        cfg = RunConfig(mode=mode, rate=rate, deadline=deadline, startup_timeout=startup_timeout,
                        save_estimates=save_estimates, warmup=warmup, deliveries=deliveries,
                        sign=None if sign is None else str(Path(sign).resolve()))
    except ValueError as exc:
        raise ScenarioError(str(exc)) from None
    run_dir = Path(out) if out is not None else default_run_dir(exp.scenario.run.name)
    hooks = Hooks(say=say or (lambda m: None), progress=progress, show_urls=on_urls, while_serving=while_serving)
    res = launch(exp, run_dir, cfg, run_id=run_id, connect=tuple(connect), router=router, dashboard=dashboard,
                 secure=Path(secure) if secure is not None else None, agents_per_process=agents_per_process, hooks=hooks)
    if res.status == EXIT_INTERRUPTED:
        raise KeyboardInterrupt
    if res.status != 0 or res.summary is None:
        raise RSEError("; ".join(res.failures) or "the run failed")
    out_res = open_run(run_dir, exp)
    out_res.summary_data = res.summary
    out_res.leaves = list(res.leaves)
    return out_res


def replay(run_dir: str | Path, *, out: str | Path | None = None,
           set: Mapping[str, Any] | Iterable[str] | None = None, rerun: Any = True,
           progress: Callable[[int, float], None] | None = None) -> RunResult:
    """Re-execute the recorded run ``run_dir`` (``rse run`` records its deliveries) in-process
    and write the run directory ``out`` (default ``RUN_DIR-replay``; ``rse replay``). With the
    run's scenario the estimates equal the run's bit for bit; ``set`` overrides keys on top
    of it (``{"estimator.variant": "linear"}``: another estimator on the same measurements
    and delivery fates); ``rerun``: the Rerun recording (True: ``out/recording.rrd``, an
    :class:`agents.dashboard.DashboardOptions`, or False). See :mod:`agents.replay` and
    docs/replay.md."""
    from .replay_dir import replay_run

    return replay_run(run_dir, out=out, set=set, rerun=rerun, progress=progress)


def chaos(scenario: str | Path, *, duration: float, faults: str | Iterable[str] | None = None, seed: int = 1,
          rate: float | None = None, out: str | Path | None = None, set: Iterable[str] = (),
          spacing: float | None = None, settle: float | None = None, budgets: Mapping[str, float] | Iterable[str] = (), hogs: int = 2,
          threshold: float | None = None, metric: str | None = None, warmup: float = 3.0, rerun: bool = True,
          say: Callable[[str], None] | None = None) -> Any:
    """A seeded soak of faults against a realtime team of ``scenario`` on this machine for
    ``duration`` wall-clock seconds (``rse chaos``, :mod:`agents.chaos`, docs/chaos.md):
    agents and the monitor killed and restarted, agents frozen, links cut, CPU hogs.
    Returns a :class:`~agents.chaos.ChaosResult`: ``rows`` (``chaos.parquet``, one per
    fault), ``failures`` (faults not recovered within ``budgets``), ``status``."""
    from .chaos import run_chaos

    return run_chaos(scenario, duration=duration, kinds=faults, seed=seed, rate=rate, out=out,
                     overrides=_override_strings(set), spacing=spacing, settle=settle, budgets=budgets, hogs=hogs,
                     threshold=threshold, metric=metric, warmup=warmup, rerun=rerun, say=say)


def sweep(scenario: str | Path, grid: Mapping[str, Iterable[Any]] | Iterable[str], *, seeds: int = 1,
          jobs: int | None = None, out: str | Path | None = None,
          set: Mapping[str, Any] | Iterable[str] | None = None,
          progress: Callable[[int, int], None] | None = None, cluster: str | None = None,
          record: bool = True) -> pd.DataFrame:
    """Run ``scenario`` over a grid of overrides and seeds (resumable: an existing ``out``
    keeps its finished runs); returns the sweep's table (``sweep.parquet``).

    ``grid`` maps keys to values (``{"network.channel.drop_p": [0.1, 0.5]}``) or is a list of
    ``KEY=V1,V2|START:STOP:STEP`` strings as ``rse sweep --grid``. ``cluster``: the address
    of a Dask scheduler (``tcp://HOST:8786``; the ``cluster`` extra); ``record``: each
    run's tagged Rerun recording (``points/ID/run.rrd``).
    """
    import pandas as pd

    from scenarios.loader import load as load_scenario
    from scenarios.loader import toml_value

    from .sweep import run_sweep

    if isinstance(grid, Mapping):
        specs = [f"{k}=" + ",".join(toml_value(v) for v in vals) for k, vals in grid.items()]
    else:
        specs = [str(g) for g in grid]
    ov = _override_strings(set)
    if out is None:
        sc, _ = load_scenario(scenario, ov)
        out = Path("runs") / f"sweep-{sc.run.name}"
    rows = run_sweep(Path(scenario), specs, seeds=seeds, jobs=jobs or os.cpu_count() or 1, out=Path(out),
                     overrides=ov, progress=progress, cluster=cluster, record=record)
    return pd.DataFrame(rows)


def boundary(scenario: str | Path, key: str, bounds: tuple[float, float], *, metric: str = "relative_error_2",
             threshold: float, seeds: int = 20, curve: tuple[str, Iterable[Any]] | None = None,
             jobs: int | None = None, cluster: str | None = None, out: str | Path | None = None,
             set: Mapping[str, Any] | Iterable[str] | None = None, tol: float = 0.005,
             max_runs: int = 90, record: bool = True) -> list[dict[str, Any]]:
    """The value of ``key`` in ``bounds`` where the median over ``seeds`` seeds of the worst
    regular agent's ``metric`` crosses ``threshold`` (``rse boundary``: probabilistic
    bisection, :mod:`agents.boundary`); with ``curve=(KEY2, values)`` one search per value.

    Returns one result per search: ``estimate``, ``search_low``/``search_high`` (the
    search's 95% interval), ``ci_low``/``ci_high`` (95% interval from the seeds, or None),
    ``runs``, ``at`` (the value of KEY2). Every run is in ``out/boundary.parquet``.
    """
    from scenarios.loader import load as load_scenario
    from scenarios.loader import toml_value

    from .boundary import run_boundary

    ov = _override_strings(set)
    vary = [f"{key}={bounds[0]}:{bounds[1]}"]
    if curve is not None:
        vary.append(f"{curve[0]}=" + ",".join(toml_value(v) for v in curve[1]))
    if out is None:
        sc, _ = load_scenario(scenario, ov)
        out = Path("runs") / f"boundary-{sc.run.name}"
    _, results = run_boundary(Path(scenario), vary, metric=metric, threshold=threshold, seeds=seeds,
                              jobs=jobs or os.cpu_count() or 1, out=Path(out), overrides=ov, cluster=cluster,
                              tol=tol, max_runs=max_runs, record=record)
    return results
