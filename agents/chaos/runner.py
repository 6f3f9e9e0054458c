"""``rse chaos``: a seeded schedule of faults against a realtime team on this machine.

:func:`run_chaos` plans the soak (:mod:`agents.chaos.schedule`), writes it with its seed
to ``OUT/chaos.json``, and per episode starts a realtime team (the launcher of ``rse run``
on a thread of its own, its loss windows carrying the schedule's link cuts), injects the
faults from the main thread (:mod:`agents.chaos.inject`), measures each one once the team
ended (:mod:`agents.chaos.measure`), marks them on the dashboard's timeline
(``chaos.rrd``, the run's recording id) and writes ``OUT/chaos.parquet``. SIGINT or SIGTERM
stops everything: the injector's processes at once, the team as ``rse run`` does.
"""

from __future__ import annotations

import contextlib
import json
import math
import signal
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from estimation.errors import RSEError, ScenarioError

from .inject import Injector
from .measure import Bound, EpisodeRecord, affected_agents, measure_fault, undeclared_rounds
from .schedule import Fault, parse_budgets, parse_kinds, plan_faults

__all__ = ["ChaosResult", "run_chaos", "chaos_bound", "EXIT_UNRECOVERED"]

EXIT_UNRECOVERED = 1
_ERROR_METRICS = ("error_2", "error_inf", "relative_error_2")


@dataclass
class ChaosResult:
    """A soak's outcome: ``rows`` one per fault (``chaos.parquet``), ``failures`` one line
    each (a fault not recovered within its budget, a team that failed), ``status`` the exit
    status (0, 1, or 130 interrupted)."""

    out: Path
    faults: list[Fault]
    rows: list[dict[str, Any]]
    bound: Bound
    failures: list[str] = field(default_factory=list)
    undeclared: int = 0
    episodes: list[Path] = field(default_factory=list)
    events: list[dict[str, Any]] = field(default_factory=list)  # the injector's, per episode
    status: int = 0


def chaos_bound(exp: Any, *, metric: str | None = None, limit: float | None = None) -> tuple[Bound, int | None]:
    """The bound a recovered agent is back inside, and the round from which the scenario's
    team, in the simulator, stays inside it (None: it does not by its horizon).

    ``metric <= limit`` when given; else the looser of the scenario's steady-state
    ``[[expect]]`` bound (of its upper bounds on an error metric, the one whose interval
    ends last, ``final`` last of all) and ``[output] convergence_threshold`` on the
    summary's convergence metric (``relative_error_2`` for a state that grows past 1e3,
    else ``error_inf``), where both bound that metric; the ``[[expect]]`` bound where only
    it does."""
    from agents.runs import simulate

    df = simulate(exp).metrics()
    x = df[(df["block"] == "x") & df["regular"]]
    with np.errstate(divide="ignore", invalid="ignore"):
        grows = bool(np.nanmax((x["error_2"] / x["relative_error_2"]).to_numpy()) > 1e3)
    conv = "relative_error_2" if grows else "error_inf"
    thr = float(exp.scenario.output.convergence_threshold)
    best: tuple[float, float, Any] | None = None
    for e in exp.scenario.expect:
        if e.max is None or e.metric not in _ERROR_METRICS:
            continue
        end = math.inf if e.over == "final" else (exp.window[1] if e.over == "window" else float(e.over[1]))
        if best is None or (end, e.max) > best[:2]:
            best = (end, e.max, e)
    if metric is not None or limit is not None:
        bound = Bound(metric or conv, float(limit if limit is not None else thr), "x", "--threshold")
    elif best is not None and (best[2].metric != conv or best[2].max >= thr):
        e = best[2]
        bound = Bound(e.metric, float(e.max), "x", e.label or "[[expect]]")
    else:
        bound = Bound(conv, thr, "x", "[output] convergence_threshold")
    err = x.pivot_table(index="k", columns="agent", values=bound.metric).to_numpy()
    bad = np.flatnonzero(~(err <= bound.limit).all(axis=1))
    inside = 0 if bad.size == 0 else (None if bad[-1] == len(err) - 1 else int(bad[-1]) + 1)
    return bound, inside


def _spacing(episodes: list[float], kinds: tuple[str, ...], settle: float, tail: float, lag: float,
             **plan: Any) -> float:
    """The largest spacing in [6, 10] s at which every kind comes at least 5 times (10 s when
    none does: a short soak)."""
    for sp in np.arange(10.0, 5.99, -0.5):
        got = plan_faults(episodes=episodes, kinds=kinds, spacing=float(sp), settle=settle, tail=tail,
                          record_lag=lag, **plan)
        counts = [sum(f.kind == k for f in got) for k in kinds]
        if min(counts) >= 5:
            return float(sp)
    return 10.0


def record_lag(rate: float) -> float:
    """Seconds of record a killed realtime monitor takes with it: the rounds it holds open
    (up to :data:`~agents.net.config.MONITOR_LAG` for a report that does not come) and at
    most a second not yet streamed to ``metrics.partial/``."""
    from agents.net.config import MONITOR_LAG

    return MONITOR_LAG / rate + 1.0


def _team_shape(exp: Any) -> tuple[list[int], list[tuple[int, int]], dict[int, list[int]]]:
    """Regular agent ids, the links between two regular agents, out-neighbours by id."""
    ids = list(exp.agent_ids)
    regular = [a for i, a in enumerate(ids) if i not in exp.byzantine]
    links = sorted({(min(ids[i], ids[j]), max(ids[i], ids[j])) for i in range(exp.N) for j in exp.in_neighbours(i)
                    if ids[i] in regular and ids[j] in regular})
    outs = {ids[i]: [ids[j] for j in exp.out_neighbours(i)] for i in range(exp.N)}
    return regular, links, outs


def _episodes(exp: Any, total: int) -> list[int]:
    """Rounds per episode: one team, unless the plant outgrows float64 sooner."""
    from scenarios.build import safe_horizon

    h = total if exp.stepper is not None else safe_horizon(exp, total)
    n = max(1, math.ceil(total / max(1, h)))
    return [math.ceil(total / n)] * n


def _cut_windows(faults: list[Fault], rate: float, exp: Any) -> dict[int, tuple[int, int]]:
    return {f.index: (int(round(f.at * rate)), int(round((f.at + f.lasts) * rate)) - 1)
            for f in faults if f.kind == "cut-link"}


def _episode_overrides(exp: Any, rounds: int, faults: list[Fault], windows: dict[int, tuple[int, int]]) -> list[str]:
    from scenarios.loader import toml_value

    ov = [f"run.rounds={rounds}" if exp.scenario.run.rounds is not None else f"run.duration={toml_value(rounds * exp.dt)}"]
    losses = [w.model_dump() for w in exp.scenario.network.channel.losses]
    idx = {a: i for i, a in enumerate(exp.agent_ids)}
    for f in faults:
        if f.kind != "cut-link":
            continue
        a, b = f.agents
        links = [[s, r] for s, r in ((a, b), (b, a)) if exp.Adj[idx[r], idx[s]]]
        losses.append({"rounds": list(windows[f.index]), "links": links})
    if losses:  # TOML inline tables
        tables = [f"{{rounds = [{int(w['rounds'][0])}, {int(w['rounds'][1])}], links = "
                  f"[{', '.join(f'[{int(s)}, {int(r)}]' for s, r in w['links'])}]}}" for w in losses]
        ov.append(f"network.channel.losses=[{', '.join(tables)}]")
    return ov


def run_chaos(scenario: str | Path, *, duration: float, kinds: str | Iterable[str] | None = None, seed: int = 1,
              rate: float | None = None, out: str | Path | None = None, overrides: Iterable[str] = (),
              spacing: float | None = None, settle: float | None = None, tail: float = 3.0,
              budgets: Mapping[str, float] | Iterable[str] = (), hogs: int = 2, threshold: float | None = None,
              metric: str | None = None, rerun: bool = True, warmup: float = 3.0,
              say: Callable[[str], None] | None = None) -> ChaosResult:
    """Run the soak (see the module); ``say(line)``: one-line notes as it goes."""
    from agents.rundir import default_run_dir, write_json
    from agents.runs import load

    say = say or (lambda line: None)
    base = list(overrides)
    kinds_t, budget_s = parse_kinds(kinds), parse_budgets(budgets)  # bad input fails before any work
    exp0 = load(scenario, set=base)
    rate = float(rate or 1.0 / exp0.dt)
    if not (duration > 0 and math.isfinite(duration)):
        raise ScenarioError(f"--duration must be a positive number of seconds, got {duration!r}")
    regular, links, outs = _team_shape(exp0)
    ep_rounds = _episodes(exp0, int(round(duration * rate)))
    bound, inside = chaos_bound(exp0, metric=metric, limit=threshold)
    if settle is None:  # the simulated team's time to be inside the bound for good, and half of it again
        settle = max(5.0, 1.5 * inside / rate) if inside is not None else 20.0
    lag = record_lag(rate)
    common: dict[str, Any] = dict(seed=seed, agents=regular, links=links, budgets=budget_s, hogs=hogs)
    episodes = [r / rate for r in ep_rounds]
    if spacing is None:
        spacing = _spacing(episodes, kinds_t, settle, tail, lag, **common)
    faults = plan_faults(episodes=episodes, kinds=kinds_t, spacing=spacing, settle=settle, tail=tail,
                         record_lag=lag, **common)
    out_dir = Path(out) if out is not None else default_run_dir(f"chaos-{exp0.scenario.run.name}")
    out_dir.mkdir(parents=True, exist_ok=True)
    windows = _cut_windows(faults, rate, exp0)
    plan = {"scenario": str(scenario), "overrides": base, "seed": seed, "rate": rate, "duration": duration,
            "spacing": spacing, "settle": settle, "tail": tail, "record_lag": lag, "episodes": ep_rounds,
            "bound": bound.__dict__, "inside_from_round": inside,
            "faults": [f.as_dict() | ({"rounds": list(windows[f.index])} if f.index in windows else {}) for f in faults]}
    write_json(out_dir / "chaos.json", plan)
    if len(ep_rounds) > 1:
        say(f"{exp0.scenario.run.name}: the plant's state would outgrow float64 within the soak; it runs as "
            f"{len(ep_rounds)} teams of {ep_rounds[0]} rounds in turn")
    say(f"{len(faults)} fault(s) every {spacing:g} s after {settle:.1f} s; recovered: {bound.metric} <= "
        f"{bound.limit:g} ({bound.source}); schedule {out_dir / 'chaos.json'}")
    res = ChaosResult(out_dir, faults, [], bound)
    stop = threading.Event()
    prev = _catch_signals(stop)
    try:
        for e, rounds in enumerate(ep_rounds):
            mine = [f for f in faults if f.episode == e]
            run_dir = out_dir if len(ep_rounds) == 1 else out_dir / f"episode-{e + 1}"
            exp = load(scenario, set=base + _episode_overrides(exp0, rounds, mine, windows))
            res.episodes.append(run_dir)
            _episode(exp, run_dir, mine, res, rate=rate, warmup=warmup, rerun=rerun, stop=stop, say=say,
                     regular=regular, outs=outs, windows=windows)
            if stop.is_set():
                res.status = 130
                break
    finally:
        for sig, h in prev.items():
            signal.signal(sig, h)
    if res.status == 0 and res.failures:
        res.status = EXIT_UNRECOVERED
    _write(out_dir, plan, res)
    return res


def _catch_signals(stop: threading.Event) -> dict[int, Any]:
    if threading.current_thread() is not threading.main_thread():
        return {}
    return {sig: signal.signal(sig, lambda s, f: stop.set()) for sig in (signal.SIGINT, signal.SIGTERM)}


def _episode(exp: Any, run_dir: Path, faults: list[Fault], res: ChaosResult, *, rate: float, warmup: float,
             rerun: bool, stop: threading.Event, say: Callable[[str], None], regular: list[int],
             outs: dict[int, list[int]], windows: dict[int, tuple[int, int]]) -> None:
    """One team: launch it on a thread, inject ``faults``, measure them."""
    from agents.dashboard import DashboardOptions
    from agents.net.config import RunConfig
    from agents.net.launcher import Hooks, launch

    inj = Injector(run_dir, rate, stop=stop, rerun=rerun, warmup=warmup)
    got: dict[str, Any] = {}

    def noted(line: str) -> None:
        inj.note(None, "say", line=line)
        say(line)

    def team() -> None:
        try:
            got["result"] = launch(exp, run_dir, RunConfig(mode="realtime", rate=rate, warmup=warmup), dashboard=(
                DashboardOptions(rrd=run_dir / "recording.rrd") if rerun else None),
                hooks=Hooks(say=noted, progress=False, stop_when=stop.is_set))
        except BaseException as exc:  # re-raised on the main thread
            got["error"] = exc

    th = threading.Thread(target=team, name="rse-chaos-team", daemon=True)
    th.start()
    try:
        if inj.wait_started(th.is_alive):
            say(f"{run_dir.name}: the team runs at {rate:g} Hz; {len(faults)} fault(s) scheduled")
            inj.run(faults, th.is_alive)
        while th.is_alive() and not stop.is_set():
            th.join(0.1)
    finally:
        if stop.is_set():
            inj.close()
        th.join()
        inj.wait_restarted(0 if stop.is_set() else 15.0)
        inj.close()
    res.events += [ev | {"episode": len(res.episodes) - 1} for ev in inj.events]
    if "error" in got:
        raise got["error"]
    result = got.get("result")
    if result is not None and result.failures and not stop.is_set():
        res.failures += [f"{run_dir.name}: {f}" for f in result.failures]
    for ev in inj.events:  # a restarted process that failed (not one the injector killed)
        if ev["what"] == "exited" and ev["status"] > 0:
            res.failures.append(f"{run_dir.name}: the restarted {ev['name']} failed (exit status {ev['status']}; "
                                f"{run_dir / 'chaos-logs'})")
    if stop.is_set() or not (run_dir / "metrics.parquet").exists():
        return
    _measure(run_dir, faults, inj, res, rate=rate, regular=regular, outs=outs, windows=windows, exp=exp)


def _measure(run_dir: Path, faults: list[Fault], inj: Injector, res: ChaosResult, *, rate: float,
             regular: list[int], outs: dict[int, list[int]], windows: dict[int, tuple[int, int]], exp: Any) -> None:
    rec = EpisodeRecord.read(run_dir, res.bound, rate, inj.t0, exp.n_rounds)
    by_fault: dict[int, list[dict[str, Any]]] = {}
    for ev in inj.events:
        by_fault.setdefault(-1 if ev["fault"] is None else ev["fault"], []).append(ev)
    rows = []
    for n, f in enumerate(faults):
        evs = by_fault.get(f.index, []) + by_fault.get(-1, [])
        nxt = faults[n + 1] if n + 1 < len(faults) else None
        nxt_begin = next((e for e in by_fault.get(nxt.index, []) if e["what"] == "begin"), None) if nxt else None
        # up to the next fault's beginning, less what the schedule leaves before it (a killed
        # monitor's record lag); the last fault up to the end of the run
        gap = 0 if nxt is None else int(round((nxt.at - f.until) * rate))
        until = (windows[nxt.index][0] if nxt is not None and nxt.index in windows else
                 rec.round_at(nxt_begin["time"]) - gap if nxt_begin else rec.err.shape[0])
        if not any(e["what"] == "begin" for e in evs) and f.index not in windows:
            continue  # not reached (the team ended first)
        rows.append(measure_fault(rec, f, evs, bound=res.bound, affected=affected_agents(f, regular, outs),
                                  regular=regular, until_round=until, window=windows.get(f.index)))
    for r in rows:
        if not r["recovered"]:
            why = f"not recovered before the next fault: {r['why']}" if r["recovered_s"] is None else \
                f"recovered after {r['recovered_s']:.2f} s"
            res.failures.append(f"fault {r['fault']} ({r['kind']}, {r['target']}, at {r['at_s']:.1f} s): {why}; "
                                f"budget {r['budget_s']:g} s")
    declared = [(r["begin_round"], r["end_round"] + int((r["recovered_s"] or 0) * rate)) if r["recovered_s"] is not None
                else (r["begin_round"], rec.err.shape[0]) for r in rows]
    res.undeclared += undeclared_rounds(rec, regular, declared)
    res.rows += rows
    last = rec.summary.get("last_round", -1)
    if not rec.summary.get("complete", False) or last != exp.n_rounds:
        res.failures.append(f"{run_dir.name}: the run's record is incomplete: rounds up to {last} of {exp.n_rounds} "
                            f"({rec.summary.get('reason', 'complete: true') if rec.summary else 'no summary.json'})")
    with contextlib.suppress(Exception):
        from agents.dashboard import log_fault_marks

        log_fault_marks(run_dir / "chaos.rrd", run_id=_run_id(run_dir), dt=exp.dt, marks=[
            (r["begin_round"], f"fault {r['fault']}: {r['kind']} {r['target']} begins") for r in rows] + [
            (r["end_round"], f"fault {r['fault']}: {r['kind']} {r['target']} ends") for r in rows])


def _run_id(run_dir: Path) -> str:
    try:
        return str(json.loads((run_dir / "team.json").read_text())["run_id"])
    except (OSError, ValueError, KeyError) as exc:
        raise RSEError(f"{run_dir}: no team.json") from exc


def _write(out: Path, plan: dict[str, Any], res: ChaosResult) -> None:
    import pandas as pd

    from agents.rundir import write_json

    cols = ["fault", "episode", "kind", "target", "at_s", "lasts_s", "begin_round", "end_round", "noticed_s",
            "rejoined_s", "recovered_s", "budget_s", "recovered", "rounds_unrecorded", "affected", "bound", "why"]
    df = pd.DataFrame(res.rows, columns=cols)
    df.to_parquet(out / "chaos.parquet", index=False)
    write_json(out / "chaos.json", plan | {"status": res.status, "failures": res.failures,
                                           "undeclared_missing_rounds": res.undeclared, "events": res.events,
                                           "episode_dirs": [str(p) for p in res.episodes], "time": time.time()})
