"""Feasible periodic patrols of mobile agents (Mitra et al. 2019, Section 3.2).

An agent ``i`` patrols the locations ``P_i = (i_1, ..., i_|P_i|)``; location ``i_r`` is
visited exactly at the rounds ``tau_r + q T_r``, ``q = 0, 1, 2, ...``, and the agent is
commuting (``sigma_i[k] = omega``, here ``None``) at every other round. The patrol is
*feasible* when (i) no two locations are visited in the same round -- locations ``r`` and
``s`` collide iff ``tau_r = tau_s (mod gcd(T_r, T_s))`` (Chinese remainder theorem) --,
(ii) every location is visited infinitely often (``T_r >= 1``), and (iii) holds by
construction. Locations are 0-based indices into the scenario's location list.

Position on the map (the paper is silent): at a visit the agent stands on the location;
while commuting it moves on the straight segment from the previous visited location to
the next one, linearly in rounds; before its first visit it waits on the first location it
will visit. For ``k >= max(tau)`` the schedule repeats with the hyper-period
``H = lcm(T_r)``; one table of ``max(tau) + H`` rounds is compiled once, so a lookup per
round is O(1).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from .errors import DesignError

#: periods of the paper's 4-cell setup (Section 8.1), cells 1..4
PAPER_PERIODS = (13, 14, 14, 14)


@dataclass(frozen=True)
class Patrol:
    """A feasible periodic patrol; validated on construction.

    Attributes
    ----------
    locations : tuple of int
        The patrolled locations ``P_i`` (0-based, distinct).
    offsets : tuple of int
        ``tau_r >= 0``: first visit of each location.
    periods : tuple of int
        ``T_r >= 1``: revisit period of each location.
    agent : int or None
        Only used to name the agent in error messages.
    """

    locations: tuple[int, ...]
    offsets: tuple[int, ...]
    periods: tuple[int, ...]
    agent: int | None = None

    def __post_init__(self) -> None:
        who = f"patrol of agent {self.agent}" if self.agent is not None else "patrol"
        for name in ("locations", "offsets", "periods"):
            vals = tuple(getattr(self, name))
            for v in vals:
                if isinstance(v, bool) or not isinstance(v, (int, np.integer)):
                    raise DesignError(f"{who}: {name} must be integers, got {v!r}")
            object.__setattr__(self, name, tuple(int(v) for v in vals))
        P, tau, T = self.locations, self.offsets, self.periods
        if not P:
            raise DesignError(f"{who}: needs at least one location")
        if not (len(P) == len(tau) == len(T)):
            raise DesignError(f"{who}: {len(P)} locations, {len(tau)} offsets and {len(T)} periods must have equal lengths")
        if len(set(P)) != len(P):
            raise DesignError(f"{who}: location listed twice in {P}")
        for loc, t, per in zip(P, tau, T):
            if loc < 0:
                raise DesignError(f"{who}: location ids are 0-based and >= 0, got {loc}")
            if per < 1:
                raise DesignError(f"{who}: location {loc}: period must be >= 1, got {per}")
            if t < 0:
                raise DesignError(f"{who}: location {loc}: offset tau must be >= 0, got {t}")
        for a in range(len(P)):
            for b in range(a + 1, len(P)):
                k = first_collision(tau[a], T[a], tau[b], T[b])
                if k is not None:
                    raise DesignError(
                        f"{who}: infeasible, locations {P[a]} (tau {tau[a]}, T {T[a]}) and {P[b]} "
                        f"(tau {tau[b]}, T {T[b]}) are both visited in round {k}"
                    )

    @property
    def hyper_period(self) -> int:
        return math.lcm(*self.periods)

    def location_at(self, k: int) -> int | None:
        """``sigma_i[k]``: the location visited in round ``k``, or None while commuting."""
        for loc, t, per in zip(self.locations, self.offsets, self.periods):
            if k >= t and (k - t) % per == 0:
                return loc
        return None

    def visits(self, start: int, stop: int) -> list[tuple[int, int]]:
        """Visits ``(round, location)`` with ``start <= round < stop``, in time order."""
        out: list[tuple[int, int]] = []
        for loc, t, per in zip(self.locations, self.offsets, self.periods):
            q0 = max(0, -(-(start - t) // per))
            out.extend((t + q * per, loc) for q in range(q0, max(q0, -(-(stop - t) // per))))
        return sorted(out)


def first_collision(tau_a: int, T_a: int, tau_b: int, T_b: int) -> int | None:
    """First round visited by both schedules ``tau_a + q T_a`` and ``tau_b + q T_b``, or None."""
    if (tau_a - tau_b) % math.gcd(T_a, T_b):
        return None
    start = max(tau_a, tau_b)
    L = math.lcm(T_a, T_b)
    for k in range(start, start + L):
        if (k - tau_a) % T_a == 0 and (k - tau_b) % T_b == 0:
            return k
    return None  # unreachable: the CRT guarantees a solution within one lcm


class PatrolSchedule:
    """A patrol compiled against the map: O(1) location and position per round.

    Parameters
    ----------
    patrol : Patrol
    positions : (N, 2) array, optional
        2-D position of every sensing location; without it only :meth:`location` works.
    """

    def __init__(self, patrol: Patrol, positions: np.ndarray | None = None) -> None:
        self._has_pos = positions is not None
        if positions is None:
            positions = np.zeros((max(patrol.locations) + 1, 2))
        pos = np.asarray(positions, dtype=float)
        if pos.ndim != 2 or pos.shape[1] != 2:
            raise DesignError(f"location positions must have shape (N, 2), got {pos.shape}")
        bad = [loc for loc in patrol.locations if loc >= pos.shape[0]]
        if bad:
            raise DesignError(f"patrol of agent {patrol.agent}: locations {bad} not among the {pos.shape[0]} locations")
        self.patrol = patrol
        self.start = max(patrol.offsets)
        self.H = patrol.hyper_period
        n_tab = self.start + self.H
        visits = patrol.visits(0, n_tab + self.H + 1)
        loc = np.full(n_tab, -1, dtype=int)
        xy = np.empty((n_tab, 2))
        times = np.array([v[0] for v in visits])
        locs = np.array([v[1] for v in visits])
        for k in range(n_tab):
            j = int(np.searchsorted(times, k, side="right")) - 1  # last visit at or before k
            if j >= 0 and times[j] == k:
                loc[k] = locs[j]
                xy[k] = pos[locs[j]]
            elif j < 0:
                xy[k] = pos[locs[0]]
            else:
                k0, k1 = times[j], times[j + 1]
                a = (k - k0) / (k1 - k0)
                xy[k] = (1 - a) * pos[locs[j]] + a * pos[locs[j + 1]]
        loc.setflags(write=False)
        xy.setflags(write=False)
        self._loc, self._xy = loc, xy

    def _index(self, k: int) -> int:
        if k < 0:
            raise DesignError(f"round must be >= 0, got {k}")
        return k if k < self._loc.shape[0] else self.start + (k - self.start) % self.H

    def location(self, k: int) -> int | None:
        """``sigma_i[k]`` (None while commuting)."""
        v = int(self._loc[self._index(k)])
        return None if v < 0 else v

    def position(self, k: int) -> np.ndarray:
        """The agent's ``(2,)`` position on the map in round ``k`` (a copy)."""
        if not self._has_pos:
            raise DesignError("this PatrolSchedule was compiled without location positions")
        return self._xy[self._index(k)].copy()

    def at(self, k: int) -> tuple[int | None, np.ndarray]:
        """``(location or None, (2,) position)`` in round ``k``."""
        if not self._has_pos:
            raise DesignError("this PatrolSchedule was compiled without location positions")
        i = self._index(k)
        v = int(self._loc[i])
        return (None if v < 0 else v), self._xy[i].copy()


def where(patrol: Patrol, k: int, *, positions: np.ndarray) -> tuple[int | None, np.ndarray]:
    """One-off lookup: ``(location or None, (2,) position)`` of ``patrol`` in round ``k``.

    Compiles the schedule each call; drivers should build a :class:`PatrolSchedule` once.
    """
    return PatrolSchedule(patrol, positions).at(k)


def cell_patrols(
    loc_cell: ArrayLike,
    *,
    agents_per_cell: int = 4,
    periods: Sequence[int] = PAPER_PERIODS,
) -> list[Patrol]:
    """The paper's intra-cell patrols (Section 8.1).

    Every agent of cell ``c`` visits every location of cell ``c`` with period
    ``periods[c]``. Agents are numbered cell by cell (cell 0: agents ``0..A-1``, ...).

    Offsets (the paper gives none): the ``R`` locations of a cell, in increasing id order
    ``rho = 0..R-1``, are visited by the cell's agent ``a`` at
    ``tau = (rho + a * (T // A)) mod T``: one location per round along the same tour, then
    ``T - R`` commuting rounds back to the start; the ``A`` agents of a cell are spread
    ``T // A`` rounds apart along the tour. The residues are distinct modulo ``T``, so the
    patrol is feasible whenever ``T >= R``.

    Parameters
    ----------
    loc_cell : (N,) ints
        Cell (0-based) of every location.
    agents_per_cell : int
    periods : sequence of int, one per cell

    Returns
    -------
    list of Patrol, agent ``c * agents_per_cell + a`` at index of the same number.
    """
    cells = np.asarray(loc_cell, dtype=int)
    K = int(cells.max()) + 1 if cells.size else 0
    if len(periods) != K:
        raise DesignError(f"cell_patrols: {len(periods)} periods given for {K} cells")
    if agents_per_cell < 1:
        raise DesignError(f"cell_patrols: agents_per_cell must be >= 1, got {agents_per_cell}")
    out = []
    for c in range(K):
        locs = [int(l) for l in np.flatnonzero(cells == c)]
        T = int(periods[c])
        if T < len(locs):
            raise DesignError(f"cell {c + 1}: period {T} is shorter than its {len(locs)} locations; no feasible patrol visits each once per period")
        for a in range(agents_per_cell):
            shift = a * (T // agents_per_cell)
            tau = tuple((rho + shift) % T for rho in range(len(locs)))
            out.append(Patrol(tuple(locs), tau, (T,) * len(locs), agent=c * agents_per_cell + a))
    return out
