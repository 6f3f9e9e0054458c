"""Strong robustness w.r.t. a source set and MEDAGs (Mitra et al. 2019, Section 4).

Graph convention as in :mod:`estimation.graphs`: agents ``0..N-1``, ``Adj[i, l] = 1``
means agent ``i`` receives from agent ``l`` (``l`` is in ``N_i``).

* Definition 3: ``C`` is r-reachable if some ``i in C`` has ``|N_i \\ C| >= r``.
* Definition 4: ``G`` is strongly r-robust w.r.t. ``S`` if every non-empty
  ``C subset V \\ S`` is r-reachable.
* Definition 2 (MEDAG ``G_j``): a spanning subgraph in which every regular non-source
  agent has ``|N_i^(j)| >= 2f + 1`` and the regular agents split into levels
  ``L_0 = S_j cap R, L_1, ...`` with every regular in-neighbour of a level-``q`` agent in
  a lower level; sources have no in-neighbours.
* Lemma 2: ``G`` contains a MEDAG iff it is strongly ``(2f+1)``-robust w.r.t. ``S_j``.

Both are decided by one peeling pass (polynomial, not a search over subsets): start from
``X_0 = S``; ``X_{q+1} = X_q`` plus every agent with at least ``r`` in-neighbours in
``X_q``. ``G`` is strongly r-robust w.r.t. ``S`` iff the pass reaches every agent: if it
stalls, the remaining set ``C`` has ``|N_i \\ C| = |N_i cap X| < r`` for all ``i in C``;
if it does not, the first agent of any ``C`` to be added had ``r`` in-neighbours outside
``C``. The MEDAG built here (the constructive half of Lemma 2, independent of which agents
are adversarial) takes the pass's rounds as levels and gives agent ``i`` of level ``q``
all its in-neighbours in ``X_{q-1}`` (this reproduces Fig. 6: cell-1 agents at level 0,
cells 2 and 4 at level 1, cell 3 at level 2). For any adversarial set the regular agents
keep these levels (possibly leaving some empty), and edges only go from lower to higher
levels, so Definition 2 holds. Using ``r = m f + 1`` gives the MEDAG of Theorem 2.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from itertools import combinations

import numpy as np

from .errors import DesignError


def _adj(Adj: np.ndarray) -> np.ndarray:
    A = np.asarray(Adj)
    if A.ndim != 2 or A.shape[0] != A.shape[1]:
        raise DesignError(f"adjacency must be square, got shape {A.shape}")
    A = (A != 0).astype(np.int64)
    np.fill_diagonal(A, 0)
    return A


def _sources(S: Iterable[int], N: int) -> np.ndarray:
    mask = np.zeros(N, dtype=bool)
    for s in S:
        if not 0 <= int(s) < N:
            raise DesignError(f"source agent {s} outside 0..{N - 1}")
        mask[int(s)] = True
    return mask


def peel(Adj: np.ndarray, sources: Iterable[int], *, r: int) -> tuple[list[list[int]], list[int]]:
    """The peeling pass: ``(levels, unreached)``.

    ``levels[0]`` are the sources; ``levels[q]`` the agents first having ``r`` in-neighbours
    among ``levels[0..q-1]``. ``unreached`` is empty iff strongly r-robust w.r.t. ``sources``.
    """
    from scipy.sparse import csr_matrix

    A = _adj(Adj)
    if r < 1:
        raise DesignError(f"robustness level r must be >= 1, got {r}")
    inside = _sources(sources, A.shape[0])
    levels = [[int(i) for i in np.flatnonzero(inside)]]
    As = csr_matrix(A)  # O(edges) per level: large sparse teams have many levels
    while True:
        new = (~inside) & (As @ inside.astype(np.int64) >= r)
        if not np.any(new):
            break
        levels.append([int(i) for i in np.flatnonzero(new)])
        inside |= new
    return levels, [int(i) for i in np.flatnonzero(~inside)]


def is_strongly_robust(Adj: np.ndarray, sources: Iterable[int], *, r: int) -> bool:
    """Definition 4: strongly ``r``-robust w.r.t. ``sources``."""
    return not peel(Adj, sources, r=r)[1]


def strong_robustness(Adj: np.ndarray, sources: Iterable[int]) -> int | float:
    """Largest ``r`` for which ``Adj`` is strongly r-robust w.r.t. ``sources``.

    0 when not even strongly 1-robust; ``math.inf`` when every agent is a source (the
    condition is vacuous).
    """
    A = _adj(Adj)
    src = set(int(s) for s in sources)
    if len(src) == A.shape[0]:
        return math.inf
    r = 0
    while is_strongly_robust(A, src, r=r + 1):
        r += 1
    return r


def is_r_reachable(Adj: np.ndarray, C: Iterable[int], *, r: int) -> bool:
    """Definition 3 (brute-force helper for small graphs and tests)."""
    A = _adj(Adj)
    C = sorted(set(int(c) for c in C))
    out = np.ones(A.shape[0], dtype=bool)
    out[C] = False
    return any(int(A[i, out].sum()) >= r for i in C)


@dataclass(frozen=True)
class Medag:
    """A mode estimation DAG (Definition 2).

    Attributes
    ----------
    mode : int or None  the mode it serves (names errors and reports)
    r : int  every non-source agent has at least ``r`` in-neighbours
    levels : tuple of tuple of int  ``levels[0]`` = sources ``S_j``
    neighbours : tuple of tuple of int  ``N_i^(j)`` for every agent (empty for sources)
    """

    mode: int | None
    r: int
    levels: tuple[tuple[int, ...], ...]
    neighbours: tuple[tuple[int, ...], ...]

    @property
    def sources(self) -> frozenset[int]:
        return frozenset(self.levels[0])

    def level_of(self, i: int) -> int:
        for q, lv in enumerate(self.levels):
            if i in lv:
                return q
        raise DesignError(f"agent {i} is not in the MEDAG")


def build_medag(
    Adj: np.ndarray,
    sources: Iterable[int],
    *,
    f: int,
    r: int | None = None,
    mode: int | None = None,
    label: str | None = None,
) -> Medag:
    """Construct a MEDAG for one mode from the baseline graph (Lemma 2, constructive).

    Parameters
    ----------
    Adj : (N, N) array  baseline graph, ``Adj[i, l] = 1``: ``i`` receives from ``l``
    sources : iterable of int  ``S_j``
    f : int >= 0  attack budget (f-local)
    r : int, optional  in-degree required of non-sources; default ``2f + 1``, use
        ``m f + 1`` for Theorem 2. Must be at least ``2f + 1``.
    mode : int, optional;  label : str, optional  name the mode in errors (e.g.
        ``"mode 14 (cell1, lambda=1.2)"``)

    Raises
    ------
    DesignError
        The graph is not strongly r-robust w.r.t. ``sources``; the message names the mode
        and the agents the pass could not reach.
    """
    if f < 0:
        raise DesignError(f"f must be >= 0, got {f}")
    r = 2 * f + 1 if r is None else int(r)
    if r < 2 * f + 1:
        raise DesignError(f"a MEDAG needs r >= 2f + 1 = {2 * f + 1}, got r = {r}")
    A = _adj(Adj)
    levels, unreached = peel(A, sources, r=r)
    if unreached:
        what = label or (f"mode {mode}" if mode is not None else "mode")
        srcs = levels[0]
        raise DesignError(
            f"{what}: no MEDAG, the graph is not strongly {r}-robust w.r.t. the source set "
            f"{srcs}; agents {unreached} cannot get {r} in-neighbours from "
            f"{'the sources' if len(levels) == 1 else 'the sources or agents reached from them'}"
        )
    N = A.shape[0]
    nb: list[tuple[int, ...]] = [()] * N
    reached = np.zeros(N, dtype=bool)
    reached[levels[0]] = True
    for lv in levels[1:]:
        for i in lv:
            nb[i] = tuple(int(l) for l in np.flatnonzero(A[i] & reached))
        reached[lv] = True
    return Medag(mode=mode, r=r, levels=tuple(tuple(lv) for lv in levels), neighbours=tuple(nb))


def is_f_local(Adj: np.ndarray, adversaries: Iterable[int], *, f: int) -> bool:
    """At most ``f`` adversaries among the in-neighbours of every regular agent."""
    A = _adj(Adj)
    bad = _sources(adversaries, A.shape[0])
    counts = A @ bad.astype(np.int64)
    return bool(np.all(counts[~bad] <= f))


def medag_violations(medag: Medag, Adj: np.ndarray, adversaries: Iterable[int], *, f: int) -> list[str]:
    """Check Definition 2 for one adversarial set; returns the violated clauses (empty: OK).

    Levels of the regular agents are recomputed from the MEDAG's edges restricted to
    ``R = V \\ A``: ``L_0 = S_j cap R`` and ``L_{q+1}`` = regular agents whose regular
    MEDAG in-neighbours all lie in ``L_0..L_q``.
    """
    A = _adj(Adj)
    N = A.shape[0]
    bad = set(int(a) for a in adversaries)
    R = [i for i in range(N) if i not in bad]
    src = medag.sources
    out = []
    for i in range(N):
        for l in medag.neighbours[i]:
            if not A[i, l]:
                out.append(f"edge {l}->{i} is not in the baseline graph")
    for i in R:
        if i in src and medag.neighbours[i]:
            out.append(f"source {i} has in-neighbours")
        if i not in src and len(medag.neighbours[i]) < 2 * f + 1:
            out.append(f"agent {i} has {len(medag.neighbours[i])} < 2f+1 in-neighbours")
    placed = {i for i in R if i in src}
    remaining = [i for i in R if i not in src]
    while remaining:
        nxt = [i for i in remaining if all(l in placed or l in bad for l in medag.neighbours[i])]
        if not nxt:
            out.append(f"agents {remaining} cannot be levelled (cycle among regular agents)")
            break
        placed.update(nxt)
        remaining = [i for i in remaining if i not in placed]
    return out


def cell_graph(K: int, per_cell: int, *, intra: bool = False) -> np.ndarray:
    """Baseline graph of Fig. 5: every agent talks with every agent of the adjacent cells.

    Cells ``c`` and ``c +- 1 (mod K)`` are adjacent (a ring; for ``K = 4`` cell 1 borders
    2 and 4 but not 3). Agents ``c * per_cell .. (c+1) * per_cell - 1`` are in cell ``c``.
    ``intra`` also joins the agents of one cell (the figure draws no such edges; they are
    never used by a MEDAG since a cell's agents share their source sets).
    """
    if K < 1 or per_cell < 1:
        raise DesignError(f"cell_graph needs K >= 1 and per_cell >= 1, got {K}, {per_cell}")
    N = K * per_cell
    cell = np.arange(N) // per_cell
    dc = (cell[:, None] - cell[None, :]) % K
    adj = (dc == 1) | (dc == K - 1)
    if intra:
        adj |= dc == 0
    adj = adj.astype(int)
    np.fill_diagonal(adj, 0)
    return adj


def attachment_graph(
    N: int,
    *,
    r: int,
    rng: np.random.Generator,
    preferential: bool = True,
    initial: Sequence[int] | None = None,
) -> np.ndarray:
    """Section 8's construction: every new agent attaches to ``r`` existing agents.

    The ``initial`` agents (default ``0..r-1``) form a clique; agents are then added in
    increasing id order, each joined (both directions) to ``r`` distinct earlier agents,
    chosen with probability proportional to ``degree + 1`` (``preferential``, as in a
    Barabasi-Albert process) or uniformly, from the ``rng`` passed in. Every agent outside ``initial`` then has ``r``
    in-neighbours added before it, so the graph is strongly ``r``-robust w.r.t. any
    source set containing ``initial`` (use ``r = 3f + 1`` for Theorem 2 with ``m = 3``).

    Returns
    -------
    (N, N) int array, symmetric.
    """
    if r < 1 or N < r:
        raise DesignError(f"attachment_graph needs 1 <= r <= N, got r={r}, N={N}")
    init = list(range(r)) if initial is None else sorted(set(int(i) for i in initial))
    if len(init) < r or any(not 0 <= i < N for i in init):
        raise DesignError(f"attachment_graph: need at least r={r} initial agents in 0..{N - 1}, got {init}")
    adj = np.zeros((N, N), dtype=int)
    for a, b in combinations(init, 2):
        adj[a, b] = adj[b, a] = 1
    present = list(init)
    for i in range(N):
        if i in init:
            continue
        pool = np.array(present)
        if preferential:
            w = adj[pool].sum(axis=1).astype(float) + 1.0
            pick = rng.choice(pool, size=r, replace=False, p=w / w.sum())
        else:
            pick = rng.choice(pool, size=r, replace=False)
        adj[i, pick] = adj[pick, i] = 1
        present.append(i)
    return adj
