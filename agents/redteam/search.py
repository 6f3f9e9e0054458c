"""The search: an Optuna study over the candidates of a :class:`~agents.redteam.space.Space`,
evaluated in parallel batches on the executor (:mod:`agents.executor`).

Each batch of ``jobs`` trials is asked, evaluated in worker processes and told in trial
order, so a search is reproducible for its seed whatever order the runs finish in. The
study lives in ``study.journal`` (Optuna's journal storage): running the same command on
the same output directory resumes it; evaluations that were running when it stopped are
marked failed and not counted.
"""

from __future__ import annotations

import json
import math
import sys
import time
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from .space import MetricSpec, Space, active_components
from .warm import warm_start

if TYPE_CHECKING:
    from scenarios.build import Experiment

__all__ = ["evaluate", "metric_value", "Evaluator", "search"]


def metric_value(exp: Experiment, res: Any, spec: MetricSpec) -> float:
    """``spec``'s value for a finished in-process run (the largest over the regular agents,
    the rounds of ``spec.over`` and the block(s); NaN when every value is NaN)."""
    from ..summary import _nanmax, _rounds

    mon = res.sim.monitor
    last = mon.last_round
    data = mon.metric(spec.metric)[: last + 1]
    rounds = _rounds(exp, spec.over, last)
    cols = np.flatnonzero(res.sim.regular)
    bcols = np.arange(len(mon.block_names)) if spec.block == "all" else np.array([mon.block_names.index(spec.block)])
    return _nanmax(data[np.ix_(rounds, cols, bcols)])


def evaluate(scenario: dict[str, Any], source: str, overrides: Sequence[str], spec: MetricSpec) -> dict[str, Any]:
    """One candidate: load the scenario with ``overrides``, simulate, return the metric
    (a worker task: module-level, picklable arguments; ``scenario`` is the scenario as
    data, since a cluster's worker may not have the file ``source`` names)."""
    from estimation.errors import ScenarioError

    from .. import runs  # the one-run core (agents.api re-exports it)

    t0 = time.perf_counter()
    try:
        exp = runs.load(scenario, set=list(overrides), source=source)
        res = runs.simulate(exp)
        value, status = metric_value(exp, res, spec), "ok"
    except ScenarioError as exc:
        value, status = math.nan, f"invalid: {exc}"
    except (ArithmeticError, ValueError, np.linalg.LinAlgError) as exc:
        value, status = math.nan, f"error: {type(exc).__name__}: {exc}"
    return {"metric": float(value), "elapsed_s": time.perf_counter() - t0, "status": status}


class Evaluator:
    """Evaluates lists of candidates on an open executor, in order."""

    def __init__(self, executor: Any, scenario: dict[str, Any], source: str, base: Sequence[str], space: Space,
                 spec: MetricSpec) -> None:
        self.ex, self.scenario, self.source = executor, scenario, source
        self.base, self.space, self.spec = tuple(base), space, spec

    def overrides(self, cand: dict[str, Any]) -> list[str]:
        return list(self.base) + self.space.overrides(cand)

    def __call__(self, cands: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
        tasks = [(self.scenario, self.source, self.overrides(c), self.spec) for c in cands]
        out: list[dict[str, Any] | None] = [None] * len(tasks)
        for i, r in self.ex.map(evaluate, tasks):
            out[i] = r
        return out  # type: ignore[return-value]


def _objective(value: float) -> float | None:
    """What the optimiser is told: NaN is a failed trial, a blown-up run the largest float."""
    if math.isnan(value):
        return None
    return min(value, sys.float_info.max)


def open_study(out: Path, seed: int, budget: int) -> Any:
    import optuna
    from optuna.storages import JournalStorage
    from optuna.storages.journal import JournalFileBackend

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # multivariate / group TPE are flagged experimental
        sampler = optuna.samplers.TPESampler(seed=seed, multivariate=True, group=True,
                                             n_startup_trials=max(5, min(20, budget // 10)))
    storage = JournalStorage(JournalFileBackend(str(out / "study.journal")))
    return optuna.create_study(study_name="redteam", storage=storage, sampler=sampler, direction="maximize",
                               load_if_exists=True)


def _row(trial: Any, index: int, phase: str, cand: dict, res: dict, overrides: list[str]) -> dict[str, Any]:
    row = {"evaluation": index, "phase": phase, "trial": None if trial is None else trial.number,
           "metric": res["metric"], "elapsed_s": res["elapsed_s"], "status": res["status"],
           "components": active_components(cand), "candidate": json.dumps(cand), "overrides": "\n".join(overrides)}
    if trial is not None:
        row.update({f"p_{k}": v for k, v in trial.params.items()})
    return row


def previous_rows(study: Any) -> list[dict[str, Any]]:
    """The evaluations a resumed study already holds (failed runs-in-progress are dropped)."""
    import optuna

    rows = []
    for t in study.get_trials(deepcopy=False):
        if t.state == optuna.trial.TrialState.RUNNING:
            study.tell(t.number, state=optuna.trial.TrialState.FAIL)
        elif "row" in t.user_attrs:
            rows.append(dict(t.user_attrs["row"]))
    rows.sort(key=lambda r: r["evaluation"])
    return rows


def search(evaluator: Evaluator, study: Any, *, budget: int, batch: int,
           on_eval: Callable[[dict[str, Any]], None] | None = None) -> list[dict[str, Any]]:
    """Evaluate up to ``budget`` candidates (counting a resumed study's); returns every
    row, in evaluation order. ``on_eval(row)`` is called for each (``row["best"]`` is the
    best metric so far)."""
    import optuna

    rows = previous_rows(study)
    if not study.get_trials(deepcopy=False):  # a new study starts from the scenario's own attacks
        for params in warm_start(evaluator.space)[:budget]:
            study.enqueue_trial(params, skip_if_exists=True)
    best = max((r["metric"] for r in rows if not math.isnan(r["metric"])), default=-math.inf)
    for r in rows:
        if on_eval is not None:
            on_eval(r)
    while len(rows) < budget:
        n = min(batch, budget - len(rows))
        trials = [study.ask() for _ in range(n)]
        cands = [evaluator.space.sample(t) for t in trials]
        results = evaluator(cands)
        for trial, cand, res in zip(trials, cands, results):
            row = _row(trial, len(rows), "search", cand, res, evaluator.overrides(cand))
            if not math.isnan(row["metric"]):
                best = max(best, row["metric"])
            row["best"] = best
            trial.set_user_attr("row", row)
            value = _objective(res["metric"])
            if value is None:
                study.tell(trial, state=optuna.trial.TrialState.FAIL)
            else:
                study.tell(trial, value)
            rows.append(row)
            if on_eval is not None:
                on_eval(row)
    return rows
