"""Realtime health of a networked run: ``summary.json``'s ``health``, its console table and
the one line that says when the machine did not keep the rate.

Per agent: the rounds it ran and the rounds it skipped (a realtime agent runs the newest
measured round and skips the older ones it had no time for). Per link ``j->i``:

* ``sent``: estimates agent ``j`` published to ``i`` (the sender's count);
* ``arrived``: those that reached ``i`` (the receiver's count, before its channel model);
* ``lost_model``: dropped by the scenario's channel model (erasures, loss windows);
* ``lost_transport``: sent, never arrived (lost by the transport, or still in flight
  when the receiver stopped: a link of a run that ends while messages fly shows a few);
  ``None`` when either end is a restarted process (its counts start at its rejoin, the
  other end's at round 0);
* ``late``: arrived after the receiver's round meant to use them had run, or delayed by
  the channel model;
* ``age_p50_ms``, ``age_p99_ms``: the age of the estimates when a round took them in
  (:mod:`agents.net.health`);
* ``stalls``: the times nothing came from ``j`` for a second (and 10 rounds) while its
  token was present (:meth:`agents.net.health.LinkHealth.stalled`).

``deadline_misses``: the plant's rounds that started after their wall-clock time. A
realtime run whose agents skipped rounds did not keep its rate: ``kept`` is false,
``skip_fraction`` the share of rounds skipped over all agents and ``kept_rate_hz`` the rate
the agents did keep (the rate times the share of rounds they ran).
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["health_section", "rate_line", "health_rows"]


def _agents(stats: dict[str, Any], agent_ids: list[int]) -> dict[str, dict[str, Any]]:
    out: dict[str, dict[str, Any]] = {}
    for aid in agent_ids:
        m = stats.get(str(aid))
        if m is None:
            continue
        ran, skipped = int(m.meta.get("rounds", 0)), int(m.meta.get("skipped", 0))
        out[str(aid)] = {"rounds": ran, "skipped": skipped,
                         "skip_fraction": round(skipped / (ran + skipped), 4) if ran + skipped else 0.0}
    return out


def _links(stats: dict[str, Any], agent_ids: list[int], links: dict[str, dict[str, int]]) -> dict[str, dict[str, Any]]:
    published: dict[str, int] = {}
    rejoined = {str(aid) for aid in agent_ids if str(aid) in stats and stats[str(aid)].meta.get("rejoined")}
    for aid in agent_ids:
        m = stats.get(str(aid))
        if m is not None and "out" in m.arrays:
            for r, n in m.arrays["out"]:
                published[f"{aid}->{int(r)}"] = int(n)
    out: dict[str, dict[str, Any]] = {}
    for aid in agent_ids:
        m = stats.get(str(aid))
        if m is None or "ages" not in m.arrays:
            continue
        for j, p50, p99, _aged, late, stalls in m.arrays["ages"]:
            key = f"{int(j)}->{aid}"
            c = links.get(key, {})
            arrived = int(c.get("sent", 0))
            sent = published.get(key)
            spans = not {str(aid), str(int(j))} & rejoined  # both counts from round 0
            out[key] = {"sent": sent, "arrived": arrived, "lost_model": int(c.get("dropped", 0)),
                        "lost_transport": max(sent - arrived, 0) if spans and sent is not None else None,
                        "late": int(late) + int(c.get("late", 0)), "stalls": int(stalls),
                        "age_p50_ms": None if p50 < 0 else float(p50), "age_p99_ms": None if p99 < 0 else float(p99)}
    return out


def health_section(stats: dict[str, Any], agent_ids: list[int], links: dict[str, dict[str, int]], *,
                   mode: str, rate: float | None, deadline_misses: int | None) -> dict[str, Any]:
    """``summary.json``'s ``health`` from the processes' final stats messages (by name:
    ``"plant"``, ``"3"``; each with ``meta`` and ``arrays``) and the receivers' link table."""
    agents = _agents(stats, agent_ids)
    ran = sum(a["rounds"] for a in agents.values())
    skipped = sum(a["skipped"] for a in agents.values())
    frac = round(skipped / (ran + skipped), 4) if ran + skipped else 0.0
    kept = skipped == 0 and not deadline_misses
    return {"mode": mode, "rate_hz": rate, "kept": kept, "skip_fraction": frac,
            "kept_rate_hz": round(rate * (1.0 - frac), 2) if rate else None,
            "deadline_misses": deadline_misses, "agents": agents, "links": _links(stats, agent_ids, links)}


def rate_line(summary: dict[str, Any]) -> str | None:
    """One line when a realtime run did not keep its rate (else None)."""
    h = summary.get("health") or {}
    if h.get("mode") != "realtime" or h.get("kept", True) or not h.get("rate_hz"):
        return None
    worst = max(h["agents"].items(), key=lambda kv: kv[1]["skip_fraction"], default=None)
    most = f" (most: agent {worst[0]}, {worst[1]['skip_fraction']:.0%})" if worst and worst[1]["skipped"] else ""
    misses = f"; the plant missed {h['deadline_misses']} round deadline(s)" if h.get("deadline_misses") else ""
    return (f"the machine did not keep {h['rate_hz']:g} Hz: the agents skipped {h['skip_fraction']:.1%} of their "
            f"rounds{most}{misses}; they kept about {_hz(h['kept_rate_hz'])} Hz")


def _hz(rate: float) -> str:
    """A rate for a sentence: 3 significant digits, no exponent (1000, 494, 48.3, 0.5)."""
    return f"{rate:.0f}" if rate >= 100 else f"{rate:.3g}"


def health_rows(summary: dict[str, Any]) -> list[list[str]]:
    """Per agent: rounds run / skipped, and over its in-links: late, stalls, lost to the model,
    lost in transport, the median of the links' p50 ages and the largest p99 (ms)."""
    h = summary.get("health") or {}
    rows = []
    for aid, a in h.get("agents", {}).items():
        into = [c for key, c in h.get("links", {}).items() if key.endswith(f"->{aid}")]
        p50 = [c["age_p50_ms"] for c in into if c["age_p50_ms"] is not None]
        p99 = [c["age_p99_ms"] for c in into if c["age_p99_ms"] is not None]
        lost_t = [c["lost_transport"] for c in into if c["lost_transport"] is not None]
        rows.append([aid, str(a["rounds"]), str(a["skipped"]), str(sum(c["late"] for c in into)),
                     str(sum(c.get("stalls", 0) for c in into)),
                     str(sum(c["lost_model"] for c in into)), str(sum(lost_t)) if lost_t else "-",
                     f"{float(np.median(p50)):.1f}" if p50 else "-", f"{max(p99):.1f}" if p99 else "-"])
    return rows


HEALTH_COLUMNS = ("agent", "rounds run", "skipped", "in: late", "in: stalls", "in: lost (model)", "in: lost (transport)",
                  "age p50 ms", "age p99 ms")
