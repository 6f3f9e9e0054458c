"""What each fault of a chaos soak did, measured from the run directory afterwards.

Rounds are the plant's: round ``k`` ticks at ``round0_at + k / rate`` (``summary.json``,
``performance.round0_at``), so an injector event at wall time ``t`` is round
``(t - round0_at) * rate``. Per fault (docs/chaos.md):

* **noticed**: how long after the fault began the run's record shows it: the target's
  first missing report (kill, freeze), the first round a cut link's receiver ran without
  a fresh message from the other end (``deliveries/``), the launcher's or the injector's
  sight of the killed monitor's exit, the first missing or out-of-bound report of any
  agent during hogs (none: the team absorbed them);
* **recovered**: how long after the fault ended (restart, SIGCONT, link back, hogs
  reaped) every affected agent's error is back inside the bound and stays there until the
  next fault: the first round after the last out-of-bound report of each, every one of
  them having reported within the last second before the next fault (a missing report is
  not out of bound: a realtime agent skips a round now and then);
* **rejoined** (kills): how long after the restart the process was back: the restarted
  agent's first report at the monitor, the restarted monitor's first recorded round;
* **rounds unrecorded**: rounds from the fault's beginning until it recovered in which
  some affected agent's report is missing (the monitor: the rounds no monitor recorded).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .schedule import Fault

__all__ = ["Bound", "EpisodeRecord", "measure_fault", "affected_agents", "undeclared_rounds"]


@dataclass(frozen=True)
class Bound:
    """The error bound a recovered agent is back inside: ``metric <= limit`` on ``block``."""

    metric: str
    limit: float
    block: str
    source: str  # where it comes from (the [[expect]] label, or the convergence threshold)


@dataclass
class EpisodeRecord:
    """One episode's run directory, read once: ``err`` ``(rounds, N)`` the bound's metric per
    round and agent (NaN: no report), the agent ids, round 0's wall time, the summary."""

    run_dir: Path
    agent_ids: list[int]
    err: np.ndarray
    round0_at: float | None
    summary: dict[str, Any]
    rate: float

    @classmethod
    def read(cls, run_dir: Path, bound: Bound, rate: float, t0_guess: float | None, n_rounds: int) -> EpisodeRecord:
        """``run_dir``'s record of rounds ``0..n_rounds`` (a round past its end: no report)."""
        import pyarrow.parquet as pq

        summary: dict[str, Any] = {}
        try:
            summary = json.loads((run_dir / "summary.json").read_text())
        except (OSError, ValueError):
            pass
        m = pq.read_table(run_dir / "metrics.parquet", columns=["k", "agent", "block", bound.metric]).to_pandas()
        m = m[m["block"] == bound.block]
        table = m.pivot_table(index="k", columns="agent", values=bound.metric, dropna=False, aggfunc="first")
        table = table.reindex(index=range(n_rounds + 1))
        round0 = (summary.get("performance") or {}).get("round0_at")
        return cls(run_dir, [int(a) for a in table.columns], table.to_numpy(dtype=float),
                   float(round0) if round0 else t0_guess, summary, rate)

    def round_at(self, t: float) -> int:
        return int(round((t - (self.round0_at or t)) * self.rate))

    def cols(self, agents: list[int]) -> list[int]:
        return [self.agent_ids.index(a) for a in agents if a in self.agent_ids]


def affected_agents(f: Fault, regular: list[int], out_neighbours: dict[int, list[int]]) -> list[int]:
    """Whose errors a fault may disturb: the target and its out-neighbours, a cut link's
    two ends, every regular agent for the monitor and the hogs."""
    if f.kind in ("kill-agent", "freeze-agent"):
        a = f.agents[0]
        return [x for x in regular if x == a or x in out_neighbours.get(a, [])]
    if f.kind == "cut-link":
        return [x for x in regular if x in f.agents]
    return list(regular)


def _first(mask: np.ndarray, start: int) -> int | None:
    idx = np.flatnonzero(mask[start:])
    return None if idx.size == 0 else int(start + idx[0])


def recovered_round(err: np.ndarray, limit: float, start: int, end: int, until: int, hold: int) -> int | None:
    """The first round ``>= end`` from which every column of ``err[start:until]`` stays
    within ``limit`` (see the module); None when not before ``until``."""
    if until <= end or err.shape[1] == 0:
        return None
    rec = end
    for c in range(err.shape[1]):
        col = err[start:until, c]
        bad = np.flatnonzero(np.isfinite(col) & (col > limit))
        after = max(end - start, int(bad[-1]) + 1 if bad.size else 0)
        good = np.flatnonzero(np.isfinite(col[after:]))
        if good.size == 0:
            return None
        tail = col[max(0, until - start - hold):]
        if not np.isfinite(tail).any():
            return None  # it stopped reporting before the next fault
        rec = max(rec, start + after + int(good[0]))
    return rec


def _cut_noticed(run_dir: Path, f: Fault, r_s: int) -> int | None:
    """The first round ``> r_s`` at which a cut link's receiver held, from the other end,
    nothing stamped ``r_s`` or later (``deliveries/``)."""
    from agents.deliveries import read_record

    try:
        record = read_record(run_dir)
    except Exception:
        return None
    firsts = []
    for rx, tx in ((f.agents[0], f.agents[1]), (f.agents[1], f.agents[0])):
        for inc in record.get(rx, []):
            if tx not in inc.in_ids:
                continue
            col = inc.stamps[:, inc.in_ids.index(tx)]
            hit = np.flatnonzero((inc.k > r_s) & (col < r_s))
            if hit.size:
                firsts.append(int(inc.k[hit[0]]))
    return min(firsts) if firsts else None


def measure_fault(rec: EpisodeRecord, f: Fault, events: list[dict[str, Any]], *, bound: Bound, affected: list[int],
                  regular: list[int], until_round: int, window: tuple[int, int] | None = None) -> dict[str, Any]:
    """One row of ``chaos.parquet`` for fault ``f`` (its events: ``begin``, ``end``, ``say``)."""
    rate = rec.rate
    begin = next((e for e in events if e["what"] == "begin"), None)
    end = next((e for e in events if e["what"] == "end"), None)
    if window is not None:  # a cut: the channel's loss window, in rounds
        r_s, r_e = window[0], window[1] + 1
    else:
        r_s = rec.round_at(begin["time"]) if begin else int(round(f.at * rate))
        r_e = rec.round_at(end["time"]) if end else r_s
    last = rec.err.shape[0]
    until = min(max(until_round, r_e), last)
    cols = rec.cols(affected)
    err = rec.err[:, cols]
    hold = max(1, int(round(rate)))
    noticed = _noticed(rec, f, begin, events, r_s, until, bound, regular)
    r_rec = recovered_round(err, bound.limit, r_s, min(r_e, until), until, hold) if r_s < last else None
    recovered_s = None if r_rec is None else max(0, r_rec - r_e) / rate
    stop = until if r_rec is None else r_rec
    missing = ~np.isfinite(err[r_s:stop]) if cols else np.zeros((0, 0), bool)
    unrec = int(missing.any(axis=1).sum()) if missing.size else 0
    if f.kind == "kill-monitor":  # the rounds no monitor recorded: no agent's report
        unrec = int((~np.isfinite(err[r_s:stop])).all(axis=1).sum()) if cols else 0
    ok = recovered_s is not None and recovered_s <= f.budget + 1e-9
    rejoined = _rejoined(rec, f, r_e, until, regular) if f.kind in ("kill-agent", "kill-monitor") else None
    return {"why": "" if r_rec is not None else _why(err, bound.limit, r_e, until, hold),
        "fault": f.index, "episode": f.episode, "kind": f.kind, "target": f.target,
        "at_s": r_s / rate, "lasts_s": (r_e - r_s) / rate, "begin_round": r_s, "end_round": r_e,
        "noticed_s": noticed, "rejoined_s": rejoined, "recovered_s": recovered_s, "budget_s": f.budget, "recovered": ok,
        "rounds_unrecorded": unrec, "affected": ",".join(map(str, affected)),
        "bound": f"{bound.metric} <= {bound.limit:g}",
    }


def _rejoined(rec: EpisodeRecord, f: Fault, r_e: int, until: int, regular: list[int]) -> float | None:
    """How long after its restart a killed process was back: the restarted agent's first
    report at the monitor, the restarted monitor's first recorded round (None: not before
    the next fault)."""
    c = rec.cols([f.agents[0]] if f.kind == "kill-agent" else regular)
    k = _first(np.isfinite(rec.err[:until, c]).any(axis=1), r_e) if c and r_e < until else None
    return None if k is None else (k - r_e) / rec.rate


def _why(err: np.ndarray, limit: float, end: int, until: int, hold: int) -> str:
    """Why a fault did not recover before ``until``: what the record shows of it."""
    tail = err[max(end, until - hold):until]
    if tail.size == 0 or until <= end:
        return "no round between its end and the next fault"
    if not np.isfinite(tail).any():
        return "no report recorded in the last second before the next fault"
    last = [c[np.isfinite(c)][-1] for c in err[end:until].T if np.isfinite(c).any()]
    if any(v > limit for v in last):
        return f"an affected agent still out of bound ({max(last):.3g}) at the next fault"
    return "an affected agent stopped reporting"


def _noticed(rec: EpisodeRecord, f: Fault, begin: dict[str, Any] | None, events: list[dict[str, Any]], r_s: int,
             until: int, bound: Bound, regular: list[int]) -> float | None:
    rate = rec.rate
    if f.kind == "kill-monitor":
        seen = [e["time"] for e in events if e["what"] in ("say", "exited") and begin and e["time"] >= begin["time"]
                and ("monitor" in e.get("line", "") or e.get("name") == "monitor")]
        return None if not seen or begin is None else round(min(seen) - begin["time"], 3)
    if f.kind == "cut-link":
        k = _cut_noticed(rec.run_dir, f, r_s)
    elif f.kind in ("kill-agent", "freeze-agent"):
        c = rec.cols([f.agents[0]])
        k = _first(~np.isfinite(rec.err[:until, c[0]]), r_s) if c else None
    else:
        e = rec.err[:until, rec.cols(regular)]
        k = _first((~np.isfinite(e) | (e > bound.limit)).any(axis=1), r_s) if e.size else None
    return None if k is None else (k - r_s) / rate


def undeclared_rounds(rec: EpisodeRecord, regular: list[int], declared: list[tuple[int, int]]) -> int:
    """Rounds outside every declared gap (``[first, last]``: each fault from its beginning
    until it recovered) in which some regular agent's report is missing."""
    e = rec.err[:, rec.cols(regular)]
    if e.size == 0:
        return 0
    miss = ~np.isfinite(e).all(axis=1)
    for a, b in declared:
        miss[max(0, a): max(0, b + 1)] = False
    return int(miss.sum())


def fmt_s(v: float | None) -> str:
    return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.2f}"
