"""Modal form, the named plants and the switched observers (7)-(8) with Schur eq. (11)."""

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from scipy import sparse

from estimation.cells import cells, diffusion
from estimation.errors import DesignError
from estimation.modal import modal_form
from estimation.patrols import Patrol, cell_patrols
from estimation.switched_observer import (
    design_agent_observers,
    observer_step,
    sampled_error_matrix,
    sampled_gain,
    source_sets,
)


def test_modal_form_round_trip_and_errors():
    rng = np.random.default_rng(1)
    lam = np.array([1.2, 0.9, -0.5, 0.3])
    T = rng.standard_normal((4, 4))
    A = T @ np.diag(lam) @ np.linalg.inv(T)
    mf = modal_form(A)
    np.testing.assert_allclose(mf.W @ A @ mf.V, np.diag(mf.lam), atol=1e-10)
    np.testing.assert_allclose(np.sort(mf.lam), np.sort(lam), atol=1e-12)
    x = rng.standard_normal((3, 4))  # leading batch axis
    np.testing.assert_allclose(mf.to_state(mf.to_modal(x)), x, atol=1e-12)
    assert mf.spectral_radius == pytest.approx(1.2)
    with pytest.raises(DesignError, match="complex eigenvalues"):
        modal_form(np.array([[0.0, 1.0], [-1.0, 0.0]]))
    with pytest.raises(DesignError, match="repeated eigenvalue"):
        modal_form(np.array([[1.0, 1.0], [0.0, 1.0]]))
    with pytest.raises(DesignError, match="must be square"):
        modal_form(np.zeros((2, 3)))
    with pytest.raises(DesignError, match=r"not decoupled: A\[0, 1\]"):
        modal_form(np.array([[1.0, 0.5], [0.0, 2.0]]), blocks=[[0], [1]])


def test_modal_rows_reads_only_the_measured_states():
    # a non-trivial modal basis: C V from the read columns equals the dense product
    rng = np.random.default_rng(4)
    T = rng.normal(size=(7, 7))
    A = T @ np.diag([0.3, 0.5, 0.7, 0.9, 1.1, 1.2, 1.4]) @ np.linalg.inv(T)  # real, distinct
    m = modal_form(A)
    C = np.zeros((2, 7))
    C[0, 2], C[1, 5], C[1, 6] = 1.0, -0.5, 2.0
    np.testing.assert_allclose(m.modal_rows(C), C @ m.V, rtol=1e-13, atol=1e-13)
    assert not m.is_identity
    # a diagonal plant is already modal: rows are returned as they are (a copy)
    d = modal_form(np.diag([0.5, 1.1, 1.2]))
    assert d.is_identity
    c = np.array([[0.0, 1.0, 0.0]])
    out = d.modal_rows(c)
    np.testing.assert_array_equal(out, c @ d.V)
    out[0, 0] = 9.0
    assert c[0, 0] == 0.0


def test_cells_model():
    m = cells(4, np.random.default_rng(0))
    assert m.A.shape == (80, 80) and len(m.loc_C) == 40
    assert not sparse.issparse(m.A)  # small: dense (no scipy.sparse in the plant's process)
    np.testing.assert_array_equal(m.A, np.diag(np.tile(np.linspace(0.5, 1.2, 20), 4)))
    assert m.block_names == ("cell1", "cell2", "cell3", "cell4")
    # location r = 3 of cell 2 (1-based) measures states 5 and 6 of cell 2
    row = m.loc_C[10 + 2][0]
    assert np.flatnonzero(row).tolist() == [20 + 4, 20 + 5]
    assert m.x0[[0, 20, 40, 60]].tolist() == [0.07, 0.05, 0.03, 0.01]
    assert cells(6, np.random.default_rng(0)).x0[[80, 100]].tolist() == [0.07, 0.05]  # cycled
    for c in range(4):  # locations inside their cell's square
        p = m.positions[m.loc_cell == c] - m.cell_origin[c]
        assert np.all((p >= 0) & (p <= m.cell_size))
    assert np.array_equal(cells(4, np.random.default_rng(0)).positions, m.positions)
    mf = modal_form(m.A, blocks=m.blocks)
    np.testing.assert_array_equal(mf.V, np.eye(80))
    big = cells(52, np.random.default_rng(0))  # 1,040 states: from SPARSE_FROM on, A is sparse
    assert sparse.issparse(big.A) and big.A.nnz == 1040  # block diagonal: only the diagonal is stored
    np.testing.assert_array_equal(big.A.toarray(), np.diag(np.tile(np.linspace(0.5, 1.2, 20), 52)))
    x, D = np.random.default_rng(2).normal(size=1040), big.A.toarray()
    for _ in range(50):  # the plant's sparse step is the dense product bit for bit
        x, xd = big.A @ x, D @ x
        np.testing.assert_array_equal(x, xd)


def test_diffusion_model():
    m = diffusion(4, np.random.default_rng(0))
    mf = modal_form(m.A, blocks=m.blocks)
    lam = mf.lam.reshape(4, 10)
    np.testing.assert_allclose(lam[:, 0], 1.0, atol=1e-12)  # one marginal mode per cell
    assert np.all(lam[:, 1:] < 1.0) and np.all(lam > 0)
    for c in range(4):
        blk = m.A[c * 10 : (c + 1) * 10, c * 10 : (c + 1) * 10]
        L = (np.eye(10) - blk) / 0.01
        pos = m.positions[c * 10 : (c + 1) * 10]
        d = np.linalg.norm(pos[:, None] - pos[None], axis=-1)
        assert np.array_equal(L != 0, (d < 15.0))  # off-diagonal: closer than 15; diagonal: degree > 0
    assert m.loc_C[13][0, 13] == 1.0 and m.loc_C[13].sum() == 1.0


@settings(max_examples=200, deadline=None)
@given(
    st.lists(st.floats(0.2, 1.5), min_size=1, max_size=4, unique=True),
    st.integers(1, 15).filter(lambda t: t % 2 == 1),
    st.integers(1, 2),
    st.floats(0.1, 0.9),
    st.booleans(),
    st.integers(0, 2**31),
)
@example(lam=[0.6394458901993607, 0.75, 0.640625, 1.0], period=1, rows=1, target=0.125, deadbeat=False, seed=0)
def test_sampled_error_matrix_is_schur(lam, period, rows, target, deadbeat, seed):
    lam = np.array(lam)
    spread = np.abs(lam[:, None] ** period - lam[None, :] ** period) + np.eye(lam.size)
    if lam.size > 1 and spread.min() < 1e-3:
        return  # nearly equal sampled modes: a legitimate but ill-posed design
    C = np.random.default_rng(seed).uniform(0.5, 2.0, (rows, lam.size))
    L, moved = sampled_gain(lam, C, period, target=target, deadbeat=deadbeat)
    M = sampled_error_matrix(lam, C, L, period)
    ev, vecs = np.linalg.eig(M)
    # the computed eigenvalues of a placed pole set are only as exact as their condition:
    # modes 1e-3 apart give eigenvector condition numbers near 1e9 (errors of about 1e-5)
    tol = 1e-6 + 1e-12 * np.linalg.cond(vecs)
    assert np.max(np.abs(ev)) < 1.0
    # modes below the target are left alone: zero gain row, eigenvalue lambda^T kept
    assert np.all(L[~moved] == 0)
    for q in np.flatnonzero(~moved):
        assert np.min(np.abs(ev - lam[q] ** period)) < 1e-9
    if moved.any() and not deadbeat:
        assert np.max(np.abs(ev)) <= max(target, np.max(np.abs(lam[~moved] ** period), initial=0)) + tol
    if deadbeat and moved.all():
        Mp = np.linalg.matrix_power(M, lam.size)
        assert np.max(np.abs(Mp)) < 1e-8 * max(1.0, np.max(np.abs(M)) ** lam.size)


def test_even_period_with_opposite_eigenvalues_is_rejected():
    """Lemma 1: lambda = +-1.1 sampled every 2 rounds are indistinguishable."""
    with pytest.raises(DesignError, match="equal lambda\\^T at period 2"):
        sampled_gain(np.array([1.1, -1.1]), np.ones((1, 2)), 2, where="agent 0, location 4")
    sampled_gain(np.array([1.1, -1.1]), np.ones((1, 2)), 3)


@pytest.mark.parametrize("model", [cells, diffusion])
def test_four_cell_observers_are_schur_with_moderate_gains(model):
    m = model(4, np.random.default_rng(0))
    mf = modal_form(m.A, blocks=m.blocks)
    patrols = cell_patrols(m.loc_cell)
    agents = [design_agent_observers(mf, m.loc_C, p, agent=i) for i, p in enumerate(patrols)]
    radii = [o.sampled_radius for a in agents for o in a.observers]
    gains = [np.abs(o.L).max() for a in agents for o in a.observers]
    assert max(radii) <= 0.5 + 1e-6
    if model is cells:
        assert max(gains) < 10.0  # the fast stable modes are left alone (no ~1e6 gains)
    S = source_sets(agents, mf.n)
    assert S[0] == frozenset(range(4)) and S[-1] == frozenset(range(12, 16))


def test_switched_observer_converges_on_its_patrol():
    """Eqs. (7)-(8) on cell 1 of the cells plant: the agent's observed modes converge."""
    m = cells(1, np.random.default_rng(0))
    mf = modal_form(m.A, blocks=m.blocks)
    p = Patrol(tuple(range(10)), tuple(range(10)), (13,) * 10, agent=0)
    ao = design_agent_observers(mf, m.loc_C, p, agent=0, deadbeat=True)
    x, v = m.x0.copy(), np.zeros(ao.size)
    for k in range(200):
        loc = p.location_at(k)
        y = None if loc is None else m.loc_C[loc] @ x
        if k % 7 == 3:
            y = None  # a missed measurement is ordinary input (open loop)
        v = observer_step(v, ao, loc, y)
        x = m.A @ x
    z = mf.to_modal(x)
    err = np.abs(v[ao.owner] - z[ao.observed]) / np.abs(z[ao.observed]).max()
    assert err.max() < 1e-12
