"""A Ugrinovskii node's local linear system as an affine map of its Riccati solutions.

Node ``i``'s dynamics (8), (17) over a step are ``s' = M s + G v`` (``s = [x_hat; e_hat;
eps_hat]``, ``v = [y; c_j; eta_j; f; f_c]``, :mod:`estimation.ugrinovskii`). Every gain is
linear in a Riccati solution: with ``Z = [C_i; W_i1; ...]`` (the rows of ``y`` and the
``c_j``) and ``P = blockdiag((D D')^-1, U_i1^-1, ...)``,

* (42): ``[L | K_1 | ...] = Ybar Z' Pbar`` (``Pbar`` with ``Ubar_ij``),
* (36), (31): ``[[L_hat | K_hat]; [L_check | K_check]] = Y[:, :n] Z' P`` (``bold C_i = [C_i
  0]``, ``bold W_ij = [W_ij 0]``: only the first ``n`` columns of ``Y`` enter),
* (44): ``[L_bar | K_bar] = [L_hat | K_hat] - [L | K]``,

so ``L C + sum_j K_j W_j = Ybar Z' Pbar Z`` and likewise for the detector's gains. The
constant part of ``(M, G)`` (``A``, ``-F Ups``, ``Omega - Gbar Ups``, ``F``, ``F_c``) is
built once (:func:`template`); :func:`system` adds the parts the gains bring, for one node
or for a stack of nodes (leading axis) with the same sizes: one definition for the node's
own refresh and for a batch's.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np

__all__ = ["Template", "template", "system"]


class Template(NamedTuple):
    """The constant part of a node's ``(M, G)`` and the factors of its gains."""

    M0: np.ndarray  # (d, d)
    G0: np.ndarray  # (d, m)
    Z: np.ndarray  # (r, n): [C_i; W_ij ...], r = p + sum p_j
    Ro: np.ndarray  # (n, r): Z' Pbar, the observer's gains per unit Ybar
    Rd: np.ndarray  # (n, r): Z' P, the detector's gains per unit Y[:, :n]
    n: int
    p: int
    controlled: bool


def template(node: Any) -> Template:
    """The :class:`Template` of a :class:`estimation.ugrinovskii._NodeBase`."""
    pb, i, n = node._pb, node.node, node._pb.n
    C, F, W = pb.C[i], pb.F[i], [pb.W[(i, j)] for j in node._nb]
    D = np.atleast_2d(pb.D[i])
    DD = D @ D.T
    Z = np.vstack([C, *W]) if W else np.asarray(C, float)
    Ro = np.hstack([np.linalg.solve(DD, C).T, *(np.linalg.solve(U, Wj).T for U, Wj in zip(node._Ub, W))])
    d, p, nf, pj = node._state_dim, node._p, node._nf, node._pj
    cols = np.cumsum([0, p] + pj + pj + [nf, nf])  # y | c_j | eta_j | f | f_c
    M0 = np.zeros((d, d))
    G0 = np.zeros((d, int(cols[-1])))
    M0[:n, :n] = pb.A
    G0[:n, cols[-3]: cols[-2]] = F
    Rd = np.zeros_like(Ro)
    if node._controlled:
        Rd = np.hstack([np.linalg.solve(DD, C).T, *(np.linalg.solve(U, Wj).T for U, Wj in zip(node._U, W))])
        Ups, Fc = pb.Upsilon[i], pb.Fc[i]
        Fbar, Gbar = Fc[:n], Fc[n:]
        M0[:n, 2 * n:] = -F @ Ups
        M0[n: 2 * n, n: 2 * n] = pb.A
        M0[n: 2 * n, 2 * n:] = -Fbar @ Ups
        M0[2 * n:, 2 * n:] = pb.Omega[i] - Gbar @ Ups
        G0[n: 2 * n, cols[-2]: cols[-1]] = Fbar
        G0[2 * n:, cols[-2]: cols[-1]] = Gbar
    return Template(M0, G0, Z, Ro, Rd, n, p, bool(node._controlled))


def system(t: Template, Ybar: np.ndarray, Y: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """``(M, G)`` of the node(s) of template ``t`` at the observer solution ``Ybar`` (41)
    and the detector solution ``Y`` (35) (None for the baseline).

    Either one node (``Ybar`` ``(n, n)``, the template's arrays as built) or a stack
    (``Ybar`` ``(B, n, n)``, ``Y`` ``(B, n + ne, n + ne)``, every template array stacked on a
    leading axis of ``B``); returns ``(d, d), (d, m)`` or ``(B, d, d), (B, d, m)``.
    """
    n, p = t.n, t.p
    r = t.Z.shape[-2]
    Go = Ybar @ t.Ro  # [L | K_j] (42)
    M = t.M0.copy()
    G = t.G0.copy()
    if not t.controlled:
        M[..., :n, :n] -= Go @ t.Z
        G[..., :n, :r] = Go
        return M, G
    assert Y is not None
    Gd = Y[..., :, :n] @ t.Rd  # [[L_hat | K_hat]; [L_check | K_check]] (36), (31)
    gains = np.concatenate([Go, Gd[..., :n, :] - Go, Gd[..., n:, :]], axis=-2)  # [L | K]; [L_bar | K_bar] (44); checks
    M[..., :, :n] -= gains @ t.Z
    M[..., n:, n: 2 * n] -= Gd @ t.Z
    G[..., :, :r] = gains
    G[..., n:, r: r + (r - p)] = Gd[..., :, p:]
    return M, G
