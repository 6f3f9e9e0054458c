"""Feasible periodic patrols (Mitra et al., Section 3.2) and the paper's 4-cell patrols."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from estimation.cells import cells
from estimation.errors import DesignError
from estimation.patrols import PAPER_PERIODS, Patrol, PatrolSchedule, cell_patrols, first_collision, where


def test_two_locations_in_the_same_round_is_rejected():
    with pytest.raises(DesignError, match=r"agent 3: infeasible, locations 0 .* and 1 .* both visited in round 8"):
        Patrol((0, 1), (0, 2), (4, 6), agent=3)
    with pytest.raises(DesignError, match="visited in round 5"):
        Patrol((2, 7), (5, 5), (7, 9))


@pytest.mark.parametrize(
    "args, msg",
    [
        (((), (), ()), "at least one location"),
        (((0, 1), (0,), (2, 2)), "equal lengths"),
        (((0, 0), (0, 1), (2, 2)), "listed twice"),
        (((0,), (0,), (0,)), "period must be >= 1"),
        (((0,), (-1,), (3,)), "offset tau must be >= 0"),
        (((-2,), (0,), (3,)), "0-based"),
        (((0,), (0.5,), (3,)), "integers"),
        (((0, 1), (0, 1), (1, 2)), "both visited"),  # T = 1 with another location
    ],
)
def test_validation_errors(args, msg):
    with pytest.raises(DesignError, match=msg):
        Patrol(*args, agent=1)


def test_paper_cell_patrols_are_feasible_and_visit_every_location_of_the_cell():
    model = cells(4, np.random.default_rng(0))
    patrols = cell_patrols(model.loc_cell, agents_per_cell=4, periods=PAPER_PERIODS)
    assert len(patrols) == 16
    for i, p in enumerate(patrols):
        c = i // 4
        assert set(p.locations) == set(np.flatnonzero(model.loc_cell == c))
        assert set(p.periods) == {PAPER_PERIODS[c]}
        T = PAPER_PERIODS[c]
        seen = [p.location_at(k) for k in range(100, 100 + T)]
        assert sorted(l for l in seen if l is not None) == sorted(p.locations)  # each once per period
        assert seen.count(None) == T - 10
    # the four agents of a cell are spread along the tour
    assert [patrols[a].location_at(0) for a in range(4)] == [0, None, 7, 4]  # tours wrap mod T
    assert [patrols[a].offsets[0] for a in range(4)] == [0, 3, 6, 9]
    with pytest.raises(DesignError, match="cell 1: period 9 is shorter than its 10 locations"):
        cell_patrols(model.loc_cell, periods=(9, 14, 14, 14))


def test_schedule_positions_follow_the_patrol():
    pos = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0]])
    p = Patrol((0, 1, 2), (1, 3, 4), (6, 6, 6), agent=0)
    sched = PatrolSchedule(p, pos)
    assert sched.at(0)[0] is None and np.allclose(sched.at(0)[1], pos[0])  # waits at first location
    assert sched.location(1) == 0
    assert sched.location(2) is None and np.allclose(sched.position(2), [5.0, 0.0])  # half-way 0 -> 1
    assert sched.location(3) == 1 and sched.location(4) == 2
    # rounds 5, 6 commute from location 2 (round 4) back to location 0 (round 7)
    assert np.allclose(sched.position(5), [10 - 10 / 3, 10 - 10 / 3])
    assert sched.location(7) == 0
    for k in range(0, 200):
        assert sched.location(k) == p.location_at(k)
    loc, xy = where(p, 1000, positions=pos)
    assert loc == p.location_at(1000) and np.allclose(xy, sched.position(1000))
    with pytest.raises(DesignError, match="not among the 3 locations"):
        PatrolSchedule(Patrol((5,), (0,), (2,)), pos)


@settings(max_examples=200, deadline=None)
@given(st.integers(0, 30), st.integers(1, 12), st.integers(0, 30), st.integers(1, 12))
def test_collision_rule_matches_brute_force(ta, Ta, tb, Tb):
    visits_a = {ta + q * Ta for q in range(400)}
    both = sorted(k for k in range(ta, ta + 400) if k in visits_a and k >= tb and (k - tb) % Tb == 0)
    got = first_collision(ta, Ta, tb, Tb)
    assert got == (both[0] if both else None)
