"""Size budgets: what a run of a scenario will cost, estimated before anything is built.

A scenario is user input, and one mistyped exponent (``run.duration = 1e18``,
``agents.per_cell = 1000000``, ``plant.params.substeps = 1e300``) asks for a run that
would not finish in a lifetime or not fit in the machine. The builder calls these checks
as soon as each size is known, before it allocates or loops over anything of that size:

* :func:`check_rounds`: the horizon (``run.rounds``, or ``run.duration / run.dt``);
* :func:`check_count`: a count the scenario asks for (agents, states, substeps);
* :func:`check_run`: the estimated memory and time of the whole run, once the plant's and
  the team's sizes are known.

Each refusal is one :class:`~estimation.errors.ScenarioError` naming the keys and the
estimate. The documented limits (:data:`LIMITS`, :data:`MAX_SECONDS`) are lifted by
``[run] force = true`` (``--set run.force=true``) for a deliberately large run; memory
beyond the machine's is refused in any case. docs/scenario-format.md ("Size budgets")
documents the figures.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from estimation.errors import ScenarioError

#: documented limits on the counts a scenario asks for (``[run] force = true`` lifts them;
#: ``points``, a sweep's values x seeds, is a limit of ``rse sweep --grid``)
LIMITS = {"rounds": 10_000_000, "agents": 100_000, "states": 100_000, "substeps": 10_000, "points": 100_000}
#: the longest estimated run (seconds of the in-process simulator) without ``force``
MAX_SECONDS = 24 * 3600.0
#: the share of the machine's memory a run's estimate may take, force or not
MEMORY_SHARE = 0.8

# rough per-unit costs of the in-process simulator on one core (README's simulator table:
# about 30 us per agent-round of bookkeeping, 25-80 ns per fused value)
_AGENT_ROUND_S = 30e-6
_FUSED_VALUE_S = 25e-9
_PLANT_FLOP_S = 1e-9
FORCE_HINT = "set run.force = true (--set run.force=true) for a deliberately large run"


def _fmt(x: float) -> str:
    return f"{x:,.0f}" if x < 1e15 else f"{x:.3g}"


def check_count(what: str, value: float, keys: str, *, force: bool, source: str | None) -> None:
    """Refuse ``value`` of ``what`` (a key of :data:`LIMITS`) beyond its documented limit."""
    limit = LIMITS[what]
    if not force and value > limit:
        raise ScenarioError(f"{keys}: {_fmt(value)} {what} exceed the limit of {_fmt(limit)} {what}; {FORCE_HINT}",
                            source=source)


def horizon_rounds(dt: float, duration: float | None, rounds: int | None) -> float:
    """The number of rounds a ``[run]`` table asks for, as a float (never overflows)."""
    if rounds is not None:
        return float(rounds)
    q = (duration or 0.0) / dt
    return q if math.isfinite(q) else math.inf


def check_rounds(dt: float, duration: float | None, rounds: int | None, *, force: bool, source: str | None) -> None:
    """``run.rounds`` or ``run.duration / run.dt`` within :data:`LIMITS` ``["rounds"]``."""
    keys = "run.rounds" if rounds is not None else "run.duration / run.dt"
    check_count("rounds", horizon_rounds(dt, duration, rounds), keys, force=force, source=source)


def machine_memory() -> int:
    """The machine's physical memory in bytes."""
    import psutil

    return int(psutil.virtual_memory().total)


@dataclass(frozen=True)
class Cost:
    """A run's estimated peak memory (bytes) and simulator time (seconds): a rough lower
    estimate, counting only the arrays every run holds and the work every round does."""

    memory: float
    seconds: float

    def describe(self) -> str:
        time = f" and {_duration(self.seconds)}" if self.seconds > 0 else ""
        return f"about {self.memory / 2**30:.3g} GiB{time}"


def _duration(s: float) -> str:
    if s < 120:
        return f"{s:.3g} s"
    if s < 2 * 3600:
        return f"{s / 60:.3g} min"
    return f"{s / 3600:.3g} h"


def estimate(*, rounds: float, agents: int, states: int, fused: float, substeps: int = 1, points: int = 1,
             keep_trajectories: bool = False) -> Cost:
    """The cost of ``points`` runs (a sweep's points) of ``rounds`` rounds.

    ``agents`` N, ``states`` n, ``fused`` the values the team fuses per round (the sum over
    agents of in-neighbours times the state dimension), ``substeps`` the plant's integration
    steps per round. Memory: the plant's dense ``A`` and its discretisation, the adjacency,
    every agent's estimate and inbox, the monitor's per-round metrics (and the trajectories
    when kept); time: bookkeeping per agent-round, fusion per value, ``n^2`` per substep.
    """
    n, N = float(states), float(agents)
    per_round_rows = (rounds + 1) * (N + 4) * 4  # error norms per agent and round, and a few totals
    memory = 8.0 * (3 * n * n + N * N + 2 * N * n + fused + per_round_rows)
    if keep_trajectories:
        memory += 8.0 * (rounds + 1) * (N + 1) * n
    per_round = N * _AGENT_ROUND_S + fused * _FUSED_VALUE_S + substeps * n * n * _PLANT_FLOP_S
    return Cost(memory=memory, seconds=points * (rounds + 1) * per_round)


def check_run(cost: Cost, keys: str, *, force: bool, source: str | None, memory: int | None = None,
              what: str = "this run") -> None:
    """Refuse a run whose estimate passes the machine's memory (:data:`MEMORY_SHARE` of it,
    always) or :data:`MAX_SECONDS` (unless ``force``); ``keys`` names what sets its size."""
    total = machine_memory() if memory is None else memory
    if cost.memory > MEMORY_SHARE * total:
        raise ScenarioError(f"{keys}: {what} needs {cost.describe()}, more than this machine's memory "
                            f"({total / 2**30:.3g} GiB); make it smaller", source=source)
    if not force and cost.seconds > MAX_SECONDS:
        raise ScenarioError(f"{keys}: {what} needs {cost.describe()}, beyond the limit of {_duration(MAX_SECONDS)}; "
                            f"{FORCE_HINT}", source=source)
