"""The library's core for one run: load a scenario, simulate it, its result as data.

:mod:`agents.api` is the public face of these functions (with the team driver and the
sweeps); modules of the library itself (the sweeps, the team launcher) import them from
here, so that the API module sits on top of what it re-exports.
"""

from __future__ import annotations

import os
import uuid
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # pragma: no cover - imported lazily at run time (keeps `import rse` light)
    import pandas as pd

    from scenarios.build import Condition, Experiment

    from .summary import ExpectationResult

_BLAS_VARS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def pin_blas_threads() -> None:
    """One BLAS thread unless the user set otherwise (effective before numpy is imported,
    and for every process started afterwards)."""
    for var in _BLAS_VARS:
        os.environ.setdefault(var, "1")


def _override_strings(set: Mapping[str, Any] | Iterable[str] | None) -> list[str]:
    """``{"run.dt": 0.01}`` or ``["run.dt=0.01"]`` -> ``["run.dt=0.01"]`` (TOML values)."""
    if set is None:
        return []
    if isinstance(set, Mapping):
        from scenarios.loader import toml_value

        return [f"{k}={toml_value(v)}" for k, v in set.items()]
    if isinstance(set, str):
        return [set]
    return [str(s) for s in set]


def load(scenario: str | Path | Mapping[str, Any], *, set: Mapping[str, Any] | Iterable[str] | None = None,
         seed: int | None = None, check_conditions: bool = True, source: str | None = None) -> Experiment:
    """Load, validate and build a scenario file.

    Parameters
    ----------
    scenario : path of a ``.toml`` scenario file, or the scenario as data (the mapping a
        TOML file reads to, e.g. ``exp.frozen`` of an earlier load: what a sweep sends to
        a worker that does not have the file)
    source : the name errors and the manifest give a scenario passed as data
    set : overrides of any key, as a mapping ``{"run.dt": 0.01}`` or ``KEY=VALUE`` strings
        (TOML values, as ``rse --set``)
    seed : overrides ``run.seed``
    check_conditions : a run's assumptions (a connected graph, redundancy) are errors;
        ``False`` builds anyway (as ``rse check`` does, to report them)

    Returns the built :class:`~scenarios.build.Experiment` (offline design done once);
    ``exp.frozen`` is the validated scenario as data, ``exp.overrides`` what was applied,
    ``exp.nominal_horizon`` the file's own horizon (a shortened run lists the bounds meant
    for it as not evaluated).
    """
    from scenarios.build import build
    from scenarios.loader import load as load_scenario
    from scenarios.loader import nominal_horizon, read_toml, validate

    ov = _override_strings(set) + ([f"run.seed={seed}"] if seed is not None else [])
    raw: dict[str, Any] | None
    if isinstance(scenario, Mapping):
        source = source or "<scenario>"
        raw = dict(scenario)
        sc, frozen = validate(raw, source=source, overrides=ov)
    else:
        source = source or str(scenario)
        sc, frozen = load_scenario(scenario, ov)
        raw = read_toml(scenario) if ov else None
    exp = build(sc, source=source, check_conditions=check_conditions)
    horizon = nominal_horizon(raw) if ov and raw is not None else sc.run.n_rounds * sc.run.dt
    return replace(exp, frozen=frozen, overrides=tuple(ov), nominal_horizon=horizon)


def load_experiment(scenario: str | Path, overrides: Iterable[str] = (), seed: int | None = None, *,
                    check_conditions: bool = True) -> tuple[Experiment, Mapping[str, Any]]:
    """:func:`load` with ``KEY=VALUE`` overrides, returning ``(experiment, frozen scenario)``."""
    exp = load(scenario, set=list(overrides), seed=seed, check_conditions=check_conditions)
    return exp, exp.frozen


def check(exp: Experiment) -> list[Condition]:
    """The conditions of the scenario's algorithm (what ``rse check`` prints), as data:
    each has ``name``, ``holds`` (True, False, or None for information) and ``detail``."""
    from scenarios.build import conditions

    return conditions(exp)


@dataclass
class RunResult:
    """The outcome of one run, from either driver.

    ``summary()`` is ``summary.json``'s content, ``expectations()`` the scenario's
    ``[[expect]]`` bounds with their measured values, ``metrics()`` the per-round errors as
    a DataFrame (the columns of ``metrics.parquet``), ``save(dir)`` writes a run directory
    (``manifest.json``, ``design.json``, ``metrics.parquet``, ``summary.json``).
    """

    experiment: Experiment | None  # None for a run directory opened without its experiment
    summary_data: dict[str, Any]
    expectation_results: list[ExpectationResult]
    run_dir: Path | None = None
    driver: str = "simulate"
    sim: Any = field(default=None, repr=False)  # agents.simulate.SimResult of an in-process run
    leaves: list[str] = field(default_factory=list)  # a team run's members that left during the run

    def summary(self) -> dict[str, Any]:
        return self.summary_data

    def expectations(self) -> list[ExpectationResult]:
        return list(self.expectation_results)

    @property
    def ok(self) -> bool:
        """Every evaluated ``[[expect]]`` bound held."""
        return not any(r.failed for r in self.expectation_results)

    def metrics(self) -> pd.DataFrame:
        """One row per (round, agent, state block): ``k, t, agent, regular, block, error_2,
        error_inf, relative_error_2``."""
        if self.sim is not None and self.experiment is not None:
            from .rundir import metrics_table

            return metrics_table(self.experiment, self.sim.monitor, self.sim.regular).to_pandas()
        if self.run_dir is None:
            raise ValueError("this result holds no metrics (no run directory)")
        import pandas as pd

        return pd.read_parquet(self.run_dir / "metrics.parquet")

    def save(self, path: str | Path, *, run_id: str | None = None) -> Path:
        """Write the run directory ``path`` (created); returns it."""
        from .rundir import write_design, write_json, write_manifest, write_metrics

        d = Path(path)
        d.mkdir(parents=True, exist_ok=True)
        if self.sim is None:
            if self.run_dir is None or self.run_dir.resolve() != d.resolve():
                raise ValueError("a team run's directory is written by the run itself (see run_dir)")
            return d
        exp = self.experiment
        assert exp is not None  # an in-process result always holds its experiment
        if not (d / "manifest.json").is_file():
            write_manifest(d, exp, exp.frozen, driver=self.driver, run_id=run_id or uuid.uuid4().hex[:12])
        write_design(d, exp)
        write_metrics(d, exp, self.sim.monitor, self.sim.regular)
        write_json(d / "summary.json", self.summary_data)
        self.run_dir = d
        return d


def _summarise_sim(exp: Experiment, res: Any) -> tuple[dict[str, Any], list[ExpectationResult]]:
    from .summary import summarise_run

    summary, results = summarise_run(exp, res.monitor, res.links)
    summary["performance"] = {"elapsed_s": res.elapsed, "agent_rounds_per_s": res.agent_rounds_per_s}
    return summary, results


def simulate(exp: Experiment, *, progress: Callable[[int, float], None] | None = None, dashboard: Any = None,
             batched: bool = True, keep_trajectories: bool = False, out: str | Path | None = None,
             run_id: str | None = None, on_done: Callable[[RunResult], None] | None = None,
             evidence: Any = None) -> RunResult:
    """Run ``exp`` in the in-process lockstep simulator (deterministic for its seed): the
    one lifecycle of an in-process run, for ``rse simulate`` and for Python alike.

    ``progress(k, worst_error)`` is called every 256 rounds; ``dashboard`` an
    :class:`agents.dashboard.Dashboard` to stream to, or its
    :class:`~agents.dashboard.DashboardOptions` (the dashboard is then opened here, with the
    run's ``run_id``, and closed on every path); ``keep_trajectories`` keeps every
    estimate and the true state (``result.sim.estimates``, ``result.sim.truth``). The
    experiment is not consumed: every call starts from fresh estimators. ``on_done(result)``
    is called once the run is complete and its directory written, while the dashboard is
    still open (``rse simulate`` prints its tables there and keeps a served viewer up).

    ``out``: the run directory, written as the run goes (:mod:`agents.recorder`: metrics
    streamed at least once a second; ``manifest.json`` and ``design.json`` first). When the
    run completes, the final files are written (``result.run_dir`` is set); when it ends
    early (an exception, Ctrl-C), the directory is left consistent with ``complete: false``
    in its ``summary.json`` before the exception propagates.

    ``evidence``: an :class:`agents.evidence.EquivocationWatch` (signed messages, digests
    compared): ``summary["evidence"]`` lists the convicted agents, ``evidence.jsonl`` the proofs.
    """
    from .dashboard import DashboardOptions
    from .simulate import simulate as run_sim

    run_id = run_id or uuid.uuid4().hex[:12]
    rec = d = own = None
    if out is not None:
        d = Path(out)
        d.mkdir(parents=True, exist_ok=True)
        (d / "summary.json").unlink(missing_ok=True)  # a new run: not the summary of an earlier one
    try:
        if d is not None:
            from .rundir import write_manifest

            if not (d / "manifest.json").is_file():
                write_manifest(d, exp, exp.frozen, driver="simulate", run_id=run_id)
        if isinstance(dashboard, DashboardOptions):
            from .dashboard import Dashboard

            own = dashboard = Dashboard(exp, run_id=run_id, options=dashboard)
        shown = dashboard  # the Rerun dashboard itself (the recorder below wraps it)
        if d is not None:
            from .recorder import Recorder
            from .rundir import write_design

            write_design(d, exp)
            rec = dashboard = Recorder(d, exp, dashboard=dashboard)
        res = run_sim(exp, progress=progress, dashboard=dashboard, batched=batched, keep_trajectories=keep_trajectories,
                      evidence=evidence)
        summary, results = _summarise_sim(exp, res)
        if evidence is not None:
            summary["evidence"] = evidence.summary()
            for j, k in evidence.convicted.items():
                if hasattr(shown, "log_conviction"):
                    shown.log_conviction(j, k)
        result = RunResult(exp, summary, results, driver="simulate", sim=res)
        if rec is not None:
            result.save(rec.run_dir)
            if evidence is not None:
                evidence.write(rec.run_dir)
            rec.done()
        if own is not None:
            own.flush()  # the recording file is complete (a served viewer stays up in on_done)
        if on_done is not None:
            on_done(result)
    except BaseException as exc:
        if d is not None:
            with deferred_signals():
                if rec is not None:
                    rec.abort(ended_by(exc))
                else:  # ended while the directory was begun (manifest, design, the stream's first
                    # segment): no round recorded
                    from .recorder import regular_mask, write_incomplete

                    write_incomplete(d, exp, None, regular_mask(exp), reason=ended_by(exc))
        raise
    finally:
        if own is not None:
            with deferred_signals():
                own.close()
    return result


def ended_by(exc: BaseException) -> str:
    """The ``reason`` of ``summary.json`` for a run ended by ``exc``."""
    from agents.net.exits import describe

    if isinstance(exc, KeyboardInterrupt):
        return f"interrupted ({exc.args[0]})" if exc.args else "interrupted (SIGINT)"
    return describe(exc)


class deferred_signals:
    """``with deferred_signals():`` SIGINT and SIGTERM wait until the block ends (the
    few hundred milliseconds in which a run directory is completed; main thread only)."""

    def __enter__(self) -> None:
        import signal
        import threading

        self._mask = None
        if threading.current_thread() is threading.main_thread():
            self._mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM})

    def __exit__(self, *exc: Any) -> None:
        import signal

        if self._mask is not None:
            signal.pthread_sigmask(signal.SIG_SETMASK, self._mask)


def open_run(run_dir: str | Path, exp: Experiment | None = None) -> RunResult:
    """A finished run directory (either driver) as a :class:`RunResult`."""
    import json

    from .summary import ExpectationResult

    d = Path(run_dir)
    summary = json.loads((d / "summary.json").read_text())
    results = [ExpectationResult.from_dict(e) for e in summary.get("expectations", [])]
    return RunResult(exp, summary, results, run_dir=d, driver="run")
