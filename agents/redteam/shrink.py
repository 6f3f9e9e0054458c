"""Shrinking a violating candidate, as property-based testing tools shrink a failing example.

From the candidate that exceeded the bound, propose simpler ones in a fixed order, evaluate
a batch, keep the first (in that order) that still exceeds, and start over; stop when no
proposal still violates or the evaluation budget is spent. Every proposal is strictly
simpler than the current candidate, so the result never has more active components:

1. fewer components: drop one attacked sensor, one Byzantine agent, one loss window, or
   switch the erasures off;
2. simpler waveforms: a ramp, sine, random or trajectory sensor attack becomes a constant one;
3. shorter windows: an attack starts later (the latest start of the space, then halfway),
   a loss window is halved;
4. rounder values: a constant strategy's value 0, every float rounded to 1, 2 or 3
   significant digits (start times upwards: a shorter window; a trajectory's direction to one
   digit), the channel seed 0;
5. smaller magnitudes: divided by 10, then by 2, down to 1e-3 of the space's bound.
"""

from __future__ import annotations

import copy
import json
import math
from collections.abc import Callable, Iterator, Sequence
from typing import Any

from .space import Space

__all__ = ["proposals", "shrink", "round_sig"]

_FLOATS = ("size", "omega", "phase", "value", "scale", "start")  # rounded in this order


def round_sig(x: float, digits: int, *, up: bool = False) -> float:
    """``x`` rounded to ``digits`` significant digits (0 stays 0); ``up``: towards +inf."""
    if x == 0 or not math.isfinite(x):
        return x
    r = float(f"{x:.{digits - 1}e}")
    if up and r < x:
        e = math.floor(math.log10(abs(x))) - digits + 1
        r = float(f"{(math.floor(x / 10.0**e) + 1) * 10.0**e:.{digits - 1}e}")
    return r


def _sig_digits(x: float) -> int:
    for d in range(1, 17):
        if round_sig(x, d) == x:
            return d
    return 17


def proposals(cand: dict[str, Any], space: Space) -> Iterator[dict[str, Any]]:
    """Simpler variants of ``cand``, simplest changes first."""
    ch = cand.get("channel", {})
    # 1. fewer components
    for group in ("sensor", "agent"):
        for i in range(len(cand[group])):
            c = copy.deepcopy(cand)
            del c[group][i]
            yield c
    for i in range(len(ch.get("losses", []))):
        c = copy.deepcopy(cand)
        del c["channel"]["losses"][i]
        yield c
    if ch.get("drop_p", 0.0) > 0:
        c = copy.deepcopy(cand)
        c["channel"]["drop_p"] = 0.0
        yield c
    # 2. simpler waveforms
    for i, s in enumerate(cand["sensor"]):
        if s["kind"] != "constant" and "constant" in space.kinds:
            c = copy.deepcopy(cand)
            c["sensor"][i] = {"bank": s["bank"], "kind": "constant", "size": s["size"], "start": s["start"]}
            yield c
    # 3. shorter windows
    latest = space.start[1]
    for group in ("sensor", "agent"):
        for i, s in enumerate(cand[group]):
            for start in (latest, 0.5 * (s["start"] + latest)):
                if start > s["start"] + 1e-9 * max(1.0, latest):
                    c = copy.deepcopy(cand)
                    c[group][i]["start"] = start
                    yield c
    for i, w in enumerate(ch.get("losses", [])):
        if w["length"] > 1:
            c = copy.deepcopy(cand)
            c["channel"]["losses"][i]["length"] = w["length"] // 2
            yield c
    # 4. rounder values: a constant strategy's value 0, floats to 1-3 significant digits, seed 0
    for group in ("sensor", "agent"):
        for i, s in enumerate(cand[group]):
            if group == "agent" and s.get("value", 0.0) != 0:
                c = copy.deepcopy(cand)
                c[group][i]["value"] = 0.0
                yield c
            for key in _FLOATS:
                if key in s:
                    for d in range(1, min(_sig_digits(s[key]), 4)):
                        # a start is rounded up (a shorter window), never past the latest start
                        r = round_sig(s[key], d, up=key == "start")
                        if key != "start" or r <= latest:
                            c = copy.deepcopy(cand)
                            c[group][i][key] = r
                            yield c
    for i, s in enumerate(cand["sensor"]):
        if "direction" in s and any(_sig_digits(x) > 1 for x in s["direction"]):
            c = copy.deepcopy(cand)
            c["sensor"][i]["direction"] = [round_sig(x, 1) for x in s["direction"]]
            yield c
    if ch.get("drop_p", 0.0) > 0:
        for d in range(1, min(_sig_digits(ch["drop_p"]), 4)):
            c = copy.deepcopy(cand)
            c["channel"]["drop_p"] = round_sig(ch["drop_p"], d)
            yield c
    if ch.get("seed", 0) != 0:
        c = copy.deepcopy(cand)
        c["channel"]["seed"] = 0
        yield c
    # 5. smaller magnitudes: divided by 10, then halved, down to 1e-3 of the space's bound
    for group, bound in (("sensor", space.amplitude), ("agent", space.value)):
        for i, s in enumerate(cand[group]):
            for key in ("size", "value", "scale"):
                for factor in (10.0, 2.0):
                    if key in s and abs(s[key]) / factor >= 1e-3 * bound:
                        c = copy.deepcopy(cand)
                        c[group][i][key] = s[key] / factor
                        yield c


def shrink(cand: dict[str, Any], value: float, space: Space, evaluate: Callable[[Sequence[dict]], list[dict]],
           violates: Callable[[float], bool], *, batch: int, max_evals: int = 100,
           on_eval: Callable[[dict, dict, bool], None] | None = None) -> tuple[dict[str, Any], float, int]:
    """The simplest candidate found that still violates: ``(candidate, metric, evaluations)``.

    ``evaluate(candidates)`` returns one result dict (``metric``, ...) per candidate, in
    order; ``on_eval(candidate, result, accepted)`` sees every evaluation.
    """
    spent = 0
    seen = {json.dumps(cand, sort_keys=True)}
    while spent < max_evals:
        props = []
        for p in proposals(cand, space):  # never evaluate a candidate twice (no cycles)
            key = json.dumps(p, sort_keys=True)
            if key not in seen:
                seen.add(key)
                props.append(p)
        accepted = False
        for lo in range(0, len(props), batch):
            chunk = props[lo:lo + min(batch, max_evals - spent)]
            if not chunk:
                break
            results = evaluate(chunk)
            spent += len(chunk)
            first = next((j for j, r in enumerate(results) if violates(r["metric"])), None)
            for j, (c, r) in enumerate(zip(chunk, results)):
                if on_eval is not None:
                    on_eval(c, r, j == first)
            if first is not None:
                cand, value, accepted = chunk[first], results[first]["metric"], True
                break
            if spent >= max_evals:
                break
        if not accepted:
            break
    return cand, value, spent
