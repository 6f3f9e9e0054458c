"""Realtime tests that assert on any machine: the rate a team keeps here, measured first.

A realtime team keeps its rate only if the machine does; an accuracy bound checked at a
rate the machine cannot keep fails with nothing wrong in the code. :func:`calibrate` runs a
short realtime probe of the scenario (``rse run --mode realtime``, its [[expect]] bounds
off) and lowers the rate until every agent ran at least ``share`` of the rounds (the
summary's ``health``, docs/networked-runtime.md); a test then runs at that rate and
asserts its bounds.
"""

from __future__ import annotations

import json
import tempfile
from pathlib import Path

from tests.conftest import rse


def kept_share(scenario: Path, rate: float, *, extra: tuple[str, ...] = ()) -> float:
    """The smallest share of rounds any agent ran in a realtime probe at ``rate`` (``extra``:
    more arguments of ``rse run``, e.g. ``--set run.duration=3`` for a short probe)."""
    with tempfile.TemporaryDirectory(prefix="rse-probe-") as tmp:
        out = Path(tmp) / "run"
        res = rse("run", str(scenario), "--mode", "realtime", "--rate", f"{rate:g}", "--out", str(out),
                  "--no-rerun", "--set", "expect=[]", *extra, timeout=180)
        if res.returncode != 0:
            raise AssertionError(f"the rate probe failed (exit {res.returncode}): {res.stderr[-2000:]}")
        agents = json.loads((out / "summary.json").read_text())["health"]["agents"]
    return min(1.0 - a["skip_fraction"] for a in agents.values())


def calibrate(scenario: Path, *, start: float, floor: float, share: float = 0.99,
              extra: tuple[str, ...] = ()) -> tuple[float, list[tuple[float, float]]]:
    """The highest rate from ``start`` down (each step: the rate kept times 0.9) at which
    every agent of a probe ran ``share`` of its rounds, not below ``floor``; and the probes
    ``(rate, share kept)``."""
    rate, probes = start, []
    for _ in range(4):
        kept = kept_share(scenario, rate, extra=extra)
        probes.append((rate, round(kept, 4)))
        if kept >= share or rate <= floor:
            break
        rate = max(floor, round(rate * kept * 0.9, 1))
    return rate, probes
