"""Summaries of a run and the scenario's ``[[expect]]`` bounds.

``summary.json`` holds, per agent and state block, the final errors, the maximum errors
over the output window and the convergence round (the first round from which the error
stays below ``[output] convergence_threshold``: ``error_inf`` for bounded plants, checked
on ``relative_error_2`` when the block's true state grows past 1e3), plus the same for the
worst regular agent, link counters and the expectations with their measured values.
``complete`` says whether the run reached its horizon; a run that ended early (a signal, a
failed plant) has ``complete: false``, the ``reason`` and ``last_round``, the last round
recorded (:mod:`agents.recorder`).

When estimators expose diagnostics or attack flags (:mod:`agents.monitor`), the summary
also has ``diagnostics`` (per agent and name: final value, largest magnitude overall and
over the window) and ``detected_attacks`` (the agents flagged in some round, and per
flagging agent the number of flagged rounds and the first and last flagged time).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from scenarios.build import Experiment
from scenarios.schema import Expectation

from .monitor import METRICS, Monitor
from .rounds import regular_mask


def _nanmax(a: np.ndarray) -> float:
    a = np.asarray(a, dtype=float)
    if a.size == 0 or np.all(np.isnan(a)):
        return math.nan
    return float(np.nanmax(a))


def _rounds(exp: Experiment, over: Any, last: int) -> np.ndarray:
    t = np.arange(last + 1) * exp.dt
    if over == "final":
        return np.array([last])
    t0, t1 = exp.window if over == "window" else over
    eps = 1e-9 * max(1.0, abs(t1))
    return np.flatnonzero((t >= t0 - eps) & (t <= t1 + eps))


def convergence_round(err: np.ndarray, threshold: float) -> int | None:
    """First round from which ``err`` (per round) stays <= threshold (None if never)."""
    bad = ~(err <= threshold)  # NaN counts as not converged
    if not bad.any():
        return 0
    last_bad = int(np.flatnonzero(bad)[-1])
    return None if last_bad == len(err) - 1 else last_bad + 1


@dataclass
class ExpectationResult:
    """One ``[[expect]]`` bound and what the run measured.

    ``ok`` is True (the bound held), False (it failed) or None (not evaluated, ``reason``
    says why: e.g. its time window lies beyond a shortened run's horizon); a bound that was
    not evaluated does not fail the command.
    """

    label: str
    value: float
    max: float | None
    min: float | None
    ok: bool | None
    reason: str | None = None

    @property
    def failed(self) -> bool:
        return self.ok is False

    @property
    def evaluated(self) -> bool:
        return self.ok is not None

    def as_dict(self) -> dict[str, Any]:
        return {"label": self.label, "value": self.value, "max": self.max, "min": self.min, "ok": self.ok,
                "reason": self.reason}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "ExpectationResult":
        """From an entry of ``summary.json``'s ``expectations`` (JSON's null value: NaN)."""
        value = d.get("value")
        return cls(label=d.get("label", ""), value=math.nan if value is None else float(value), max=d.get("max"),
                   min=d.get("min"), ok=d.get("ok"), reason=d.get("reason"))


def describe(e: Expectation) -> str:
    if e.label:
        return e.label
    who = "worst regular agent" if e.agents == "regular" else f"worst of agents {e.agents}"
    over = e.over if isinstance(e.over, str) else f"t in [{e.over[0]:g}, {e.over[1]:g}]"
    block = "any block" if e.block == "all" else f"block {e.block}"
    return f"max {e.metric} ({who}, {block}, {over})"


def outside_horizon(exp: Experiment, e: Expectation) -> str | None:
    """Why ``e`` cannot be evaluated on a run of ``exp``'s horizon (None: it can).

    A bound on a time window that ends after the run's last round cannot be judged; nor,
    when the run is shorter than the scenario file's own horizon (``--set run.rounds=...``,
    ``exp.nominal_horizon``), a bound on the ``final`` round or on the default output window
    (the last quarter of the horizon): those bounds are for the file's horizon.
    """
    T = exp.n_rounds * exp.dt
    T0 = exp.nominal_horizon if exp.nominal_horizon is not None else T
    shortened = T < T0 - 1e-9 * max(1.0, T0)
    if e.over == "final":
        if shortened:
            return f"the run is shortened to t = {T:g}; the bound is for the final round of the scenario's horizon, t = {T0:g}"
        return None
    if e.over == "window" and exp.scenario.output.window is None:
        if shortened:
            return (f"the run is shortened to t = {T:g}; the bound is for the output window of the scenario's horizon, "
                    f"t in [{0.75 * T0:g}, {T0:g}]")
        return None
    t0, t1 = exp.window if e.over == "window" else e.over
    if t1 <= T + 1e-9 * max(1.0, abs(t1)):
        return None
    what = "the output window" if e.over == "window" else "its window"
    return f"{what} t in [{t0:g}, {t1:g}] ends after the run's horizon t = {T:g}"


def evaluate(exp: Experiment, mon: Monitor, regular: np.ndarray) -> list[ExpectationResult]:
    """The scenario's ``[[expect]]`` bounds on the metrics the monitor recorded; a bound
    whose window lies beyond the horizon is listed as not evaluated, with the reason."""
    last = mon.last_round
    out = []
    for e in exp.scenario.expect:
        reason = outside_horizon(exp, e)
        if reason is not None:
            out.append(ExpectationResult(describe(e), math.nan, e.max, e.min, None, reason))
            continue
        data = mon.metric(e.metric)[: last + 1]
        rounds = _rounds(exp, e.over, last)
        if e.agents == "regular":
            cols = np.flatnonzero(regular)
        else:
            cols = np.array([exp.agent_ids.index(a) for a in e.agents])
        bcols = np.arange(len(mon.block_names)) if e.block == "all" else np.array([mon.block_names.index(e.block)])
        sel = data[np.ix_(rounds, cols, bcols)]
        value = _nanmax(sel)
        ok = not math.isnan(value)
        if e.max is not None:
            ok = ok and value <= e.max
        if e.min is not None:
            ok = ok and value >= e.min
        out.append(ExpectationResult(describe(e), value, e.max, e.min, ok))
    return out


def summarise(exp: Experiment, mon: Monitor, regular: np.ndarray, links: dict[str, dict[str, int]],
              rejected: dict[str, dict[str, int]] | None = None, *, complete: bool = True,
              reason: str | None = None) -> dict[str, Any]:
    """``summary.json``. ``complete=False`` marks a run that ended early (``reason`` says
    why); ``last_round`` is always the last round recorded."""
    last = mon.last_round
    win = _rounds(exp, "window", last)
    thr = exp.scenario.output.convergence_threshold
    agents: dict[str, Any] = {}
    data = {m: mon.metric(m)[: last + 1] for m in METRICS}  # relative_error_2 is computed when read: once
    for i, aid in enumerate(exp.agent_ids):
        blocks = {}
        for b, name in enumerate(mon.block_names):
            rec: dict[str, Any] = {}
            for m in METRICS:
                series = data[m][:, i, b]
                rec[f"final_{m}"] = float(series[last])
                rec[f"window_max_{m}"] = _nanmax(series[win])
            grows = _nanmax(mon.truth_norm[: last + 1, b]) > 1e3
            conv_metric = "relative_error_2" if grows else "error_inf"
            rec["convergence_round"] = convergence_round(data[conv_metric][:, i, b], thr)
            blocks[name] = rec
        agents[str(aid)] = {"regular": bool(regular[i]), "blocks": blocks}
    worst: dict[str, Any] = {}
    reg_ids = [str(a) for a, r in zip(exp.agent_ids, regular) if r]
    for name in mon.block_names:
        rec = {}
        for key in agents[reg_ids[0]]["blocks"][name] if reg_ids else []:
            vals = [agents[a]["blocks"][name][key] for a in reg_ids]
            if key == "convergence_round":
                rec[key] = None if any(v is None for v in vals) else max(vals)
            else:
                rec[key] = _nanmax(np.array(vals, dtype=float))
        worst[name] = rec
    out = {
        "scenario": exp.scenario.run.name,
        "complete": complete,
        **({} if complete else {"reason": reason or "the run ended early"}),
        "last_round": last,
        "rounds": last,
        "t_final": last * exp.dt,
        "window": list(exp.window),
        "convergence_threshold": thr,
        "agents": agents,
        "worst_regular": worst,
        "links": links,
        "rejected": rejected or {},
    }
    out.update(diagnostics_summary(exp, mon))
    return out


def summarise_run(exp: Experiment, mon: Monitor, links: dict[str, dict[str, int]],
                  rejected: dict[str, dict[str, int]] | None = None, *, complete: bool = True,
                  reason: str | None = None) -> tuple[dict[str, Any], list[ExpectationResult]]:
    """A run's ``summary.json`` (:func:`summarise`, with its ``expectations``) and the
    expectations :func:`evaluate` judged, as both drivers write them; ``links``:
    :func:`agents.rounds.links_table` of the receivers' counters."""
    regular = regular_mask(exp)
    results = evaluate(exp, mon, regular)
    summary = summarise(exp, mon, regular, links, rejected, complete=complete, reason=reason)
    summary["expectations"] = [r.as_dict() for r in results]
    return summary, results


def diagnostics_summary(exp: Experiment, mon: Monitor) -> dict[str, Any]:
    """``diagnostics`` and ``detected_attacks`` of ``summary.json`` (empty when no
    estimator exposes them)."""
    last = mon.last_round
    if last < 0:
        return {}
    win = _rounds(exp, "window", last)
    out: dict[str, Any] = {}
    if mon.diagnostics:
        per: dict[str, Any] = {}
        for i, aid in enumerate(exp.agent_ids):
            rec = {}
            for name, arr in mon.diagnostics.items():
                series = arr[: last + 1, i]
                if np.all(np.isnan(series)):
                    continue
                rec[name] = {"final": float(series[last]), "max_abs": _nanmax(np.abs(series)),
                             "window_max_abs": _nanmax(np.abs(series[win]))}
            if rec:
                per[str(aid)] = rec
        out["diagnostics"] = per
    if mon.flags is not None:
        flags = mon.flags[: last + 1]
        by_agent: dict[str, Any] = {}
        for i, aid in enumerate(exp.agent_ids):
            col = flags[:, i]
            if np.all(np.isnan(col)):
                continue
            up = np.flatnonzero(col == 1.0)
            by_agent[str(aid)] = {
                "flagged_rounds": int(up.size),
                "first_t": float(up[0] * exp.dt) if up.size else None,
                "last_t": float(up[-1] * exp.dt) if up.size else None,
                "flagged_at_end": bool(col[last] == 1.0),
            }
        out["detected_attacks"] = {
            "agents": [int(a) for a in exp.agent_ids if by_agent.get(str(a), {}).get("flagged_rounds")],
            "by_agent": by_agent,
        }
    return out
