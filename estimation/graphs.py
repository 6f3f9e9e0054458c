"""Communication graphs: construction, Laplacian, connectivity, algebraic connectivity.

Agents are numbered ``0..N-1`` here (the scenario layer maps its 1-based ids). An
adjacency matrix ``Adj[i, j] = 1`` means that agent ``i`` receives from agent ``j``
(``j`` is an in-neighbour of ``i``), so the Laplacian row ``i`` sums over in-neighbours
as in Lee, Kim, Shim's ``L = D - A``.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np

from .errors import DesignError


def ring(N: int, *, directed: bool = False) -> np.ndarray:
    """Ring adjacency; directed: ``i`` receives from ``i - 1``."""
    if N < 2:
        raise DesignError(f"a ring needs at least 2 agents, got {N}")
    Adj = np.zeros((N, N), dtype=int)
    for i in range(N):
        Adj[i, (i - 1) % N] = 1
        if not directed:
            Adj[i, (i + 1) % N] = 1
    np.fill_diagonal(Adj, 0)
    return Adj


def complete(N: int) -> np.ndarray:
    """All-to-all adjacency."""
    return np.ones((N, N), dtype=int) - np.eye(N, dtype=int)


def from_edges(N: int, edges: Iterable[Sequence[int]], *, directed: bool = False) -> np.ndarray:
    """Adjacency from 0-based edges ``(j, i)`` meaning ``j -> i`` (both ways if undirected)."""
    Adj = np.zeros((N, N), dtype=int)
    for e in edges:
        j, i = int(e[0]), int(e[1])
        if not (0 <= i < N and 0 <= j < N):
            raise DesignError(f"edge {tuple(e)} names an agent outside 0..{N - 1}")
        if i == j:
            raise DesignError(f"edge {tuple(e)} is a self-loop")
        Adj[i, j] = 1
        if not directed:
            Adj[j, i] = 1
    return Adj


def laplacian(Adj: np.ndarray) -> np.ndarray:
    """``L = D - Adj`` with ``D`` the in-degrees."""
    Adj = np.asarray(Adj, dtype=float)
    return np.diag(Adj.sum(axis=1)) - Adj


def is_undirected(Adj: np.ndarray) -> bool:
    return bool(np.array_equal(Adj, Adj.T))


def algebraic_connectivity(Adj: np.ndarray) -> float:
    """``lambda_2(L)`` of an undirected graph (0 when disconnected)."""
    if not is_undirected(Adj):
        raise DesignError("lambda_2 is defined here for undirected graphs only")
    ev = np.sort(np.linalg.eigvalsh(laplacian(Adj)))
    return float(ev[1]) if len(ev) > 1 else 0.0


def components(Adj: np.ndarray) -> list[list[int]]:
    """Weakly connected components (0-based agent lists), largest first."""
    import networkx as nx

    G = nx.from_numpy_array(np.asarray(Adj), create_using=nx.DiGraph)
    comps = [sorted(c) for c in nx.weakly_connected_components(G)]
    return sorted(comps, key=len, reverse=True)


def is_strongly_connected(Adj: np.ndarray) -> bool:
    import networkx as nx

    G = nx.from_numpy_array(np.asarray(Adj).T, create_using=nx.DiGraph)  # edge j->i
    return nx.is_strongly_connected(G)


def in_neighbours(Adj: np.ndarray, i: int) -> list[int]:
    return [int(j) for j in np.flatnonzero(Adj[i])]


#: largest team whose r-robustness is computed by enumeration (3^N subset pairs)
ROBUSTNESS_MAX_N = 9


def r_robustness(Adj: np.ndarray) -> int | None:
    """The largest ``r`` for which the graph is r-robust (LeBlanc, Zhang, Koutsoukos, Sundaram,
    IEEE JSAC 2013, Def. 6): every two disjoint nonempty agent sets ``S1``, ``S2`` have one
    that is r-reachable (an agent of it with at least ``r`` in-neighbours outside it).
    By enumeration of the ``3^N`` assignments; None above :data:`ROBUSTNESS_MAX_N` agents."""
    from itertools import product

    A = np.asarray(Adj) != 0
    N = A.shape[0]
    if N > ROBUSTNESS_MAX_N:
        return None
    if N < 2:
        return 0
    best = N
    for labels in product((0, 1, 2), repeat=N):  # 1: in S1, 2: in S2, 0: in neither
        lab = np.array(labels)
        reach = []
        for s in (1, 2):
            inside = lab == s
            if not inside.any():
                break
            outside_in = A[inside][:, ~inside].sum(axis=1)  # per agent of S: its in-neighbours outside S
            reach.append(int(outside_in.max()))
        else:
            best = min(best, max(reach))
    return best
