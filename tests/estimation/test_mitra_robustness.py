"""Strong r-robustness, Lemma 2 and MEDAG construction (Mitra et al., Section 4)."""

from itertools import chain, combinations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from estimation.errors import DesignError
from estimation.robustness import (
    attachment_graph,
    build_medag,
    cell_graph,
    is_f_local,
    is_r_reachable,
    is_strongly_robust,
    medag_violations,
    strong_robustness,
)


def subsets(items):
    items = list(items)
    return chain.from_iterable(combinations(items, k) for k in range(1, len(items) + 1))


def brute_strongly_robust(adj, S, r):
    """Definition 4 literally: every non-empty C outside S is r-reachable."""
    rest = [i for i in range(adj.shape[0]) if i not in S]
    return all(is_r_reachable(adj, C, r=r) for C in subsets(rest))


@st.composite
def graph_and_sources(draw):
    n = draw(st.integers(2, 8))
    bits = draw(st.lists(st.booleans(), min_size=n * n, max_size=n * n))
    adj = np.array(bits, dtype=int).reshape(n, n)
    np.fill_diagonal(adj, 0)
    S = draw(st.sets(st.integers(0, n - 1), max_size=n))
    return adj, sorted(S)


@settings(max_examples=250, deadline=None)
@given(graph_and_sources(), st.integers(0, 2))
def test_lemma2_medag_exists_iff_strongly_2f1_robust(case, f):
    adj, S = case
    r = 2 * f + 1
    robust = brute_strongly_robust(adj, S, r)
    assert is_strongly_robust(adj, S, r=r) == robust
    if not robust:
        with pytest.raises(DesignError, match=r"mode 7: no MEDAG, the graph is not strongly \d+-robust .* agents \["):
            build_medag(adj, S, f=f, mode=7)
        return
    medag = build_medag(adj, S, f=f, mode=7)
    assert medag.sources == frozenset(S)
    # Definition 2 for every f-local adversarial set (a MEDAG does not depend on it)
    n = adj.shape[0]
    for A in chain([()], subsets(range(n))):
        if len(A) <= n and is_f_local(adj, A, f=f):
            assert medag_violations(medag, adj, A, f=f) == []


@settings(max_examples=150, deadline=None)
@given(graph_and_sources())
def test_strong_robustness_is_the_largest_r(case):
    adj, S = case
    r = strong_robustness(adj, S)
    if len(S) == adj.shape[0]:
        assert r == float("inf")
        return
    assert r == 0 or brute_strongly_robust(adj, S, r)
    assert not brute_strongly_robust(adj, S, r + 1)


def test_four_cell_medag_levels_match_fig6():
    adj = cell_graph(4, 4)
    medag = build_medag(adj, range(4), f=1, r=4, mode=0)
    assert medag.levels == ((0, 1, 2, 3), (4, 5, 6, 7, 12, 13, 14, 15), (8, 9, 10, 11))
    assert medag.neighbours[8] == (4, 5, 6, 7, 12, 13, 14, 15)  # cell 3 hears cells 2 and 4
    assert medag.neighbours[5] == (0, 1, 2, 3)
    assert medag.neighbours[0] == ()
    assert medag.level_of(9) == 2
    # agent 5 (the paper's agent 5, 0-based 4) Byzantine: 1-local, Definition 2 holds
    assert is_f_local(adj, [4], f=1)
    assert medag_violations(medag, adj, [4], f=1) == []
    for c in range(4):
        assert strong_robustness(adj, range(4 * c, 4 * c + 4)) == 4


def test_omission_graph_is_only_2f1_robust():
    """Section 8.1, Fig. 11: cell 3 hears only agents 5-7 of cell 2 (0-based 4-6)."""
    adj = cell_graph(4, 4)
    adj[8:12, 12:16] = adj[12:16, 8:12] = 0
    adj[8:12, 4:8] = 0
    adj[8:12, 4:7] = 1
    assert strong_robustness(adj, range(4)) == 3
    build_medag(adj, range(4), f=1, r=3, mode=0)
    with pytest.raises(DesignError, match=r"cell1 mode: no MEDAG, .* strongly 4-robust .* agents \[8, 9, 10, 11\]"):
        build_medag(adj, range(4), f=1, r=4, label="cell1 mode")


def test_medag_needs_r_at_least_2f1():
    with pytest.raises(DesignError, match="r >= 2f \\+ 1 = 3"):
        build_medag(cell_graph(4, 4), range(4), f=1, r=2)


@pytest.mark.parametrize("preferential", [True, False])
@pytest.mark.parametrize("seed", range(5))
def test_attachment_graph_is_strongly_3f1_robust(seed, preferential):
    f = 1
    adj = attachment_graph(16, r=3 * f + 1, rng=np.random.default_rng(seed), preferential=preferential)
    assert np.array_equal(adj, adj.T) and np.all(np.diag(adj) == 0)
    assert np.all(adj[4:].sum(axis=1) >= 4)
    for extra in ([], [7], [5, 11]):
        assert strong_robustness(adj, [0, 1, 2, 3] + extra) >= 4
    build_medag(adj, range(4), f=f, r=4)
    # the same seed gives the same graph
    again = attachment_graph(16, r=4, rng=np.random.default_rng(seed), preferential=preferential)
    assert np.array_equal(adj, again)
