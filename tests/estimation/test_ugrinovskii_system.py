"""The local system ``(M, G)`` of a Ugrinovskii node as an affine map of its Riccati
solutions (estimation.ugrinovskii_system) equals the gain-by-gain construction of (8),
(17) with the gains (42), (36), (31), (44); stacked nodes equal single ones."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from estimation.hinf_riccati import difference_gains, filter_gains, split_detector_gains
from estimation.ugrinovskii_system import system, template

pytest.importorskip("cvxpy")

SCEN = Path(__file__).resolve().parents[2] / "scenarios"


def explicit_system(node) -> tuple[np.ndarray, np.ndarray]:
    """``(M, G)`` gain by gain, as the module docstring of estimation.ugrinovskii writes (8), (17)."""
    pb, i, n = node._pb, node.node, node._pb.n
    C, F, W = pb.C[i], pb.F[i], [pb.W[(i, j)] for j in node._nb]
    L, K = filter_gains(node._obs.Y, C=C, D=pb.D[i], W=W, U=node._Ub)  # (42)
    d, p, nf, pj = node._state_dim, node._p, node._nf, node._pj
    M, G = np.zeros((d, d)), np.zeros((d, node._input_dim()))
    cols = np.cumsum([0, p] + pj + pj + [nf, nf])  # y | c_j | eta_j | f | f_c
    c_sl = [slice(cols[1 + a], cols[2 + a]) for a in range(len(pj))]
    e_sl = [slice(cols[1 + len(pj) + a], cols[2 + len(pj) + a]) for a in range(len(pj))]
    f_sl, fc_sl = slice(cols[-3], cols[-2]), slice(cols[-2], cols[-1])
    KW = lambda Ks: sum((Kj @ Wj for Kj, Wj in zip(Ks, W)), np.zeros((Ks[0].shape[0], n)))
    X, E = slice(0, n), slice(n, 2 * n)
    M[X, X] = pb.A - L @ C - KW(K)
    G[X, 0:p], G[X, f_sl] = L, F
    for a, Kj in enumerate(K):
        G[X, c_sl[a]] = Kj
    if node._controlled:
        Eps = slice(2 * n, d)
        Ups, Fc = pb.Upsilon[i], pb.Fc[i]
        Fbar, Gbar = Fc[:n], Fc[n:]
        Lb, Kb = filter_gains(node._det.Y, C=np.hstack([C, np.zeros((p, node._ne))]), D=pb.D[i],
                              W=[np.hstack([Wj, np.zeros((Wj.shape[0], node._ne))]) for Wj in W], U=node._U)
        Lh, Lc, Kh, Kc = split_detector_gains(Lb, Kb, n=n)  # (36), (31)
        Lbar, Kbar = difference_gains(Lh, Kh, L, K)  # (44)
        M[X, Eps] = -F @ Ups
        M[E, X] = -Lbar @ C - KW(Kbar)
        M[E, E] = pb.A - Lh @ C - KW(Kh)
        M[E, Eps] = -Fbar @ Ups
        M[Eps, X] = M[Eps, E] = -Lc @ C - KW(Kc)
        M[Eps, Eps] = pb.Omega[i] - Gbar @ Ups
        G[E, 0:p], G[Eps, 0:p] = Lbar, Lc
        for a in range(len(K)):
            G[E, c_sl[a]], G[E, e_sl[a]] = Kbar[a], Kh[a]
            G[Eps, c_sl[a]], G[Eps, e_sl[a]] = Kc[a], Kc[a]
        G[E, fc_sl], G[Eps, fc_sl] = Fbar, Gbar
    return M, G


@pytest.mark.parametrize("name", ["ugrinovskii_biasing.toml", "ugrinovskii_baseline.toml", "ugrinovskii_detector_attack.toml"])
def test_affine_system_equals_the_gains_of_the_paper(name: str) -> None:
    from agents.api import load_experiment
    from agents.simulate import make_channel, make_nodes

    exp, _ = load_experiment(SCEN / name, ("expect=[]",), None)
    nodes = [nd.estimator for nd in make_nodes(exp, make_channel(exp))]
    for steps in (0, 1, 40):  # along the Riccati flows (the gains move most at first)
        for m in nodes:
            for _ in range(steps):
                for fl in m._flows():
                    fl.step()
        Ms, Gs = [], []
        for m in nodes:
            M, G = m._system()
            M0, G0 = explicit_system(m)
            assert M.shape == M0.shape and G.shape == G0.shape
            assert np.max(np.abs(M - M0)) <= 1e-13 * np.max(np.abs(M0))
            assert np.max(np.abs(G - G0)) <= 1e-13 * np.max(np.abs(G0))
            assert np.count_nonzero(G0) == np.count_nonzero(G)  # the same blocks filled
            Ms.append(M)
            Gs.append(G)
        # the stacked call (a batch's refresh) equals the nodes' own, bit for bit
        tp = [template(m) for m in nodes]
        st = tp[0]._replace(**{f: np.stack([getattr(t, f) for t in tp]) for f in ("M0", "G0", "Z", "Ro", "Rd")})
        Yd = np.stack([m._det.Y for m in nodes]) if nodes[0]._controlled else None
        M, G = system(st, np.stack([m._obs.Y for m in nodes]), Yd)
        assert np.array_equal(M, np.stack(Ms)) and np.array_equal(G, np.stack(Gs))
