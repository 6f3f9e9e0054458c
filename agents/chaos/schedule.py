"""The fault schedule of ``rse chaos``: pure data, a function of the seed.

A soak of ``duration`` seconds is cut into *episodes* (one team each: a plant whose state
outgrows float64 within the soak runs as several teams in turn, each within its safe
horizon), and each episode into *slots* of ``spacing`` seconds after ``settle`` seconds
in which the team converges. One fault per slot, so that each one's recovery is measured
before the next begins. The kinds come in cycles, each cycle a seeded permutation of the
chosen kinds: a soak with ``c`` slots per kind holds every kind at least ``c`` times.

Kinds (see docs/chaos.md):

* ``kill-agent``: SIGKILL an agent process, restart it ``lasts`` seconds later
  (``rse agent --id I --team RUN_DIR/team.json``, plug-and-play);
* ``kill-monitor``: SIGKILL the monitor, restart it ``lasts`` seconds later;
* ``freeze-agent``: SIGSTOP an agent process, SIGCONT ``lasts`` seconds later;
* ``cut-link``: both directions of a link between two agents drop everything for
  ``lasts`` seconds (a loss window of the channel model: every process knows it);
* ``cpu-hog``: ``hogs`` processes spin for ``lasts`` seconds, then are reaped.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import asdict, dataclass, replace

import numpy as np

from estimation.errors import ScenarioError

__all__ = ["KINDS", "BUDGETS", "LASTS", "Fault", "plan_faults", "parse_kinds", "parse_budgets"]

KINDS = ("kill-agent", "kill-monitor", "freeze-agent", "cut-link", "cpu-hog")
#: seconds after a fault ends (restart, SIGCONT, link back, hogs reaped) within which the
#: affected agents' errors must be back inside the bound
BUDGETS = {"kill-agent": 8.0, "kill-monitor": 8.0, "freeze-agent": 6.0, "cut-link": 6.0, "cpu-hog": 6.0}
#: how long a fault lasts, seconds: drawn uniformly in [low, high] (at most a third of a slot)
LASTS = {"kill-agent": (0.5, 1.5), "kill-monitor": (0.5, 1.5), "freeze-agent": (1.0, 2.0), "cut-link": (1.0, 3.0),
         "cpu-hog": (2.0, 4.0)}
_STREAM = 42  # the schedule's stream of the seed


@dataclass(frozen=True)
class Fault:
    """One fault: ``at`` seconds after round 0 of its episode, for ``lasts`` seconds.

    ``agents``: the agent(s) it targets (a link: its two ends; none for the monitor or the
    hogs); ``budget``: seconds after its end within which it must be recovered; ``until``:
    when the next fault of the episode begins (or the episode ends), the end of the window
    in which its recovery is looked for."""

    index: int
    kind: str
    episode: int
    at: float
    lasts: float
    agents: tuple[int, ...]
    budget: float
    until: float
    hogs: int = 0

    @property
    def target(self) -> str:
        if self.kind == "cut-link":
            return f"link {self.agents[0]}<->{self.agents[1]}"
        if self.kind == "cpu-hog":
            return f"{self.hogs} hog(s)"
        if self.kind == "kill-monitor":
            return "monitor"
        return f"agent {self.agents[0]}"

    def as_dict(self) -> dict:
        return asdict(self) | {"agents": list(self.agents), "target": self.target}


def parse_kinds(text: str | Iterable[str] | None) -> tuple[str, ...]:
    """``"kill-agent,cut-link"`` (or a list) into kinds; None: every kind."""
    if text is None:
        return KINDS
    items = [s.strip() for s in (text.split(",") if isinstance(text, str) else text) if s.strip()]
    bad = [s for s in items if s not in KINDS]
    if bad or not items:
        raise ScenarioError(f"--faults: unknown fault kind(s) {', '.join(bad) or '(none given)'}; "
                            f"valid: {', '.join(KINDS)}")
    return tuple(dict.fromkeys(items))


def parse_budgets(items: Iterable[str] | Mapping[str, float]) -> dict[str, float]:
    """``KIND=SECONDS`` strings (``--budget kill-agent=12``) over :data:`BUDGETS`."""
    out = dict(BUDGETS)
    pairs = items.items() if isinstance(items, Mapping) else [tuple(s.split("=", 1)) if "=" in s else (s, "")
                                                              for s in items]
    for kind, value in pairs:
        if kind not in KINDS:
            raise ScenarioError(f"--budget {kind}={value}: unknown fault kind; valid: {', '.join(KINDS)}")
        try:
            v = float(value)
        except ValueError:
            raise ScenarioError(f"--budget {kind}={value}: expected KIND=SECONDS") from None
        if not (v >= 0 and math.isfinite(v)):
            raise ScenarioError(f"--budget {kind}={value}: seconds must be finite and >= 0")
        out[kind] = v
    return out


def _kinds(rng: np.random.Generator, kinds: Sequence[str]) -> Iterator[str]:
    """Cycles of the kinds, each a seeded permutation."""
    while True:
        yield from (kinds[int(i)] for i in rng.permutation(len(kinds)))


def plan_faults(*, episodes: Sequence[float], kinds: Sequence[str], seed: int, agents: Sequence[int],
                links: Sequence[tuple[int, int]], spacing: float, settle: float, tail: float,
                budgets: Mapping[str, float] | None = None, hogs: int = 2, record_lag: float = 0.0) -> list[Fault]:
    """The faults of a soak whose episodes last ``episodes`` seconds each (see the module).

    ``agents``: the agents that may be killed or frozen (the regular ones); ``links``: the
    agent pairs that may be cut; ``record_lag``: seconds of record a killed monitor takes
    with it (the rounds it held open): a ``kill-monitor`` comes that much later in its slot,
    and the fault before it is measured up to where that record begins. Deterministic in
    its arguments."""
    budgets = dict(BUDGETS) | dict(budgets or {})
    if "cut-link" in kinds and not links:
        raise ScenarioError("--faults cut-link: the team has no link between two regular agents")
    if not agents and any(k in kinds for k in ("kill-agent", "freeze-agent")):
        raise ScenarioError("--faults: the team has no regular agent to kill or freeze")
    rng = np.random.default_rng([seed, _STREAM])
    order = _kinds(rng, kinds)
    kind = next(order)
    faults: list[Fault] = []
    for episode, length in enumerate(episodes):
        t = settle
        while True:
            pre = record_lag if kind == "kill-monitor" else 0.0
            at = round(float(t + pre), 3)
            if at + spacing > length - tail + 1e-9:
                break
            if faults and faults[-1].episode == episode:
                faults[-1] = replace(faults[-1], until=round(float(t), 3))
            faults.append(_fault(rng, len(faults), kind, episode, at, length, spacing, agents, links, budgets, hogs))
            t, kind = at + spacing, next(order)
    return faults


def _fault(rng: np.random.Generator, n: int, kind: str, episode: int, at: float, until: float, spacing: float,
           agents: Sequence[int], links: Sequence[tuple[int, int]], budgets: Mapping[str, float], hogs: int) -> Fault:
    low, high = LASTS[kind]
    high = min(high, spacing / 3)
    lasts = round(float(rng.uniform(min(low, high), high)), 2)
    if kind in ("kill-agent", "freeze-agent"):
        who: tuple[int, ...] = (int(agents[int(rng.integers(len(agents)))]),)
    elif kind == "cut-link":
        a, b = links[int(rng.integers(len(links)))]
        who = (int(a), int(b))
    else:
        who = ()
    return Fault(n, kind, episode, at, lasts, who, float(budgets[kind]), round(float(until), 3),
                 hogs if kind == "cpu-hog" else 0)
