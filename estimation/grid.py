"""A power grid as a plant: the linearised swing dynamics of its generators on the DC network,
Kron-reduced to the generator buses, with phasor measurement units (PMUs) as sensors.

Pure numpy: the network arrives as branch data (``scenarios.plugins.grid`` reads it from
pandapower). Per unit on the system base, angles in rad, frequencies in rad/s.

DC network (the DC power-flow model): a branch ``f -> t`` of series reactance ``x`` and
off-nominal tap ratio ``tau`` carries ``b (theta_f - theta_t)``, ``b = 1 / (x tau)``; the bus
injections are ``p = B theta`` with the weighted Laplacian ``B`` (:func:`susceptance_matrix`).

Kron reduction to the generator buses ``g`` (the others ``l`` carry no inertia: their
balance ``p_l = B_lg theta_g + B_ll theta_l`` is algebraic)::

    theta_l = B_ll^-1 (p_l - B_lg theta_g)
    p_e,g   = B_red theta_g + B_gl B_ll^-1 p_l,    B_red = B_gg - B_gl B_ll^-1 B_lg

Swing equations (Kundur, Power System Stability and Control, 1994, eq. 3.207, linearised
about the operating point; ``delta`` the rotor angle = the generator bus angle)::

    delta' = omega
    M omega' = p_g - p_e,g - D omega = -B_red delta - D omega + K p,   K = [I, -B_gl B_ll^-1]

with ``p`` the vector of bus injections (mechanical power at a generator bus, minus the loads).
The state is ``x = (delta_1..delta_G, omega_1..omega_G)``; the model's input is a load change
``u`` at chosen buses (a load increase is a negative injection: ``B = [0; -M^-1 K S]``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from .errors import DesignError


def susceptance_matrix(n_bus: int, f: np.ndarray, t: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The DC network's weighted Laplacian ``B`` ``(n_bus, n_bus)``: branch ``k`` joins buses
    ``f[k]`` and ``t[k]`` with susceptance ``b[k]`` (``1 / (x tau)``, p.u.)."""
    f, t, b = np.asarray(f, dtype=int), np.asarray(t, dtype=int), np.asarray(b, dtype=float)
    if not (f.shape == t.shape == b.shape):
        raise DesignError(f"branch arrays must have one shape, got {f.shape}, {t.shape}, {b.shape}")
    if f.size and (min(f.min(), t.min()) < 0 or max(f.max(), t.max()) >= n_bus):
        raise DesignError(f"branch ends must be buses 0..{n_bus - 1}")
    if not np.all(np.isfinite(b)):
        raise DesignError("branch susceptances must be finite (a zero reactance?)")
    B = np.zeros((n_bus, n_bus))
    np.add.at(B, (f, t), -b)
    np.add.at(B, (t, f), -b)
    np.add.at(B, (f, f), b)
    np.add.at(B, (t, t), b)
    return B


def kron_reduce(B: np.ndarray, keep: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Eliminate the buses not in ``keep`` (``G`` kept of ``n``).

    Returns ``(B_red (G, G), K (G, n), T (n, G + n))``: the reduced Laplacian, the map from
    bus injections to the kept buses' electrical injections (``p_e = B_red theta_g + ...``
    becomes ``B_red theta_g = K p`` at rest), and the map ``theta = T [theta_g; p]`` from the
    kept angles and the injections back to every bus angle.
    """
    n = B.shape[0]
    keep = np.asarray(keep, dtype=int)
    drop = np.setdiff1d(np.arange(n), keep)
    Bll = B[np.ix_(drop, drop)]
    Blg = B[np.ix_(drop, keep)]
    try:
        Sl = np.linalg.solve(Bll, np.hstack([Blg, np.eye(drop.size)])) if drop.size else np.zeros((0, keep.size))
    except np.linalg.LinAlgError:
        raise DesignError("the buses without a generator do not all connect to one (B_ll is singular)") from None
    if drop.size and not np.all(np.isfinite(Sl)):
        raise DesignError("the buses without a generator do not all connect to one (B_ll is singular)")
    X = Sl[:, :keep.size]  # B_ll^-1 B_lg
    Y = Sl[:, keep.size:]  # B_ll^-1
    B_red = B[np.ix_(keep, keep)] - B[np.ix_(keep, drop)] @ X
    K = np.zeros((keep.size, n))
    K[:, keep] = np.eye(keep.size)
    K[:, drop] = -B[np.ix_(keep, drop)] @ Y
    T = np.zeros((n, keep.size + n))
    T[keep, :keep.size] = np.eye(keep.size)
    T[drop, :keep.size] = -X
    T[np.ix_(drop, keep.size + drop)] = Y
    return 0.5 * (B_red + B_red.T), K, T


@dataclass(frozen=True)
class SwingModel:
    """The Kron-reduced swing dynamics of a grid (module docstring).

    Attributes
    ----------
    gen_bus : (G,) int array, the generator buses (0-based bus positions), increasing
    M, D : (G,) arrays, inertia ``2 H S_g / (omega_s S_base)`` and damping (p.u.)
    B_red : (G, G), K : (G, n_bus), T : (n_bus, G + n_bus) -- see :func:`kron_reduce`
    input_bus : (p,) int array, the buses whose load change is the input ``u``
    """

    gen_bus: np.ndarray
    M: np.ndarray
    D: np.ndarray
    B_red: np.ndarray
    K: np.ndarray
    T: np.ndarray
    input_bus: np.ndarray

    @property
    def G(self) -> int:
        return int(self.gen_bus.size)

    @property
    def A(self) -> np.ndarray:
        """``(2G, 2G)``: ``[[0, I], [-M^-1 B_red, -M^-1 D]]``."""
        G = self.G
        A = np.zeros((2 * G, 2 * G))
        A[:G, G:] = np.eye(G)
        A[G:, :G] = -self.B_red / self.M[:, None]
        A[G:, G:] = -np.diag(self.D / self.M)
        return A

    @property
    def B(self) -> np.ndarray:
        """``(2G, p)``: a load increase ``u`` at ``input_bus`` (``[0; -M^-1 K S]``)."""
        Bu = np.zeros((2 * self.G, self.input_bus.size))
        Bu[self.G:] = -self.K[:, self.input_bus] / self.M[:, None]
        return Bu

    def pmu_rows(self, bus: int) -> np.ndarray:
        """``(2, 2G)``: the angle and frequency rows of a PMU at generator bus ``bus``."""
        where = np.flatnonzero(self.gen_bus == bus)
        if where.size != 1:
            raise DesignError(f"bus {bus} has no generator: a PMU reads a generator bus (the Kron-reduced state)")
        C = np.zeros((2, 2 * self.G))
        C[0, where[0]] = 1.0
        C[1, self.G + where[0]] = 1.0
        return C

    def equilibrium(self, p: np.ndarray, *, ref: int, angle: float = 0.0) -> np.ndarray:
        """The rest state ``(2G,)`` under constant bus injections ``p`` ``(n_bus,)`` (balanced:
        ``sum p = 0``), with the angle of generator bus ``ref`` set to ``angle``:
        ``omega = 0`` and ``B_red delta = K p`` (``A x + K``-input ``= 0``)."""
        p = np.asarray(p, dtype=float)
        r = int(np.flatnonzero(self.gen_bus == ref)[0])
        others = np.delete(np.arange(self.G), r)
        rhs = self.K @ p - self.B_red[:, r] * angle
        delta = np.empty(self.G)
        delta[r] = angle
        delta[others] = np.linalg.solve(self.B_red[np.ix_(others, others)], rhs[others])
        return np.concatenate([delta, np.zeros(self.G)])

    def bus_angles(self, x: np.ndarray, p: np.ndarray) -> np.ndarray:
        """Every bus angle ``(n_bus,)`` from the state ``x`` and the bus injections ``p``."""
        return self.T @ np.concatenate([np.asarray(x, dtype=float)[:self.G], np.asarray(p, dtype=float)])


def swing_model(B: np.ndarray, gen_bus: np.ndarray, *, M: np.ndarray, D: np.ndarray,
                input_bus: np.ndarray) -> SwingModel:
    """Build :class:`SwingModel` from the DC Laplacian ``B`` and per-generator ``M``, ``D``."""
    gen_bus = np.asarray(gen_bus, dtype=int)
    if gen_bus.size == 0 or np.any(np.diff(gen_bus) <= 0):
        raise DesignError("generator buses must be distinct and increasing, at least one")
    M, D = np.asarray(M, dtype=float), np.asarray(D, dtype=float)
    if M.shape != gen_bus.shape or D.shape != gen_bus.shape:
        raise DesignError(f"M and D need one entry per generator bus ({gen_bus.size})")
    if not (np.all(M > 0) and np.all(D >= 0)):
        raise DesignError("inertias must be > 0 and dampings >= 0")
    B_red, K, T = kron_reduce(B, gen_bus)
    return SwingModel(gen_bus=gen_bus, M=M, D=D, B_red=B_red, K=K, T=T,
                      input_bus=np.asarray(input_bus, dtype=int))


def inertia(H: ArrayLike, S: ArrayLike, *, base_mva: float, f_hz: float) -> np.ndarray:
    """``M = 2 H S / (omega_s S_base)`` (p.u. power s^2 / rad), ``H`` in s on rating ``S`` (MVA)."""
    return 2.0 * np.asarray(H, dtype=float) * np.asarray(S, dtype=float) / (2 * np.pi * f_hz * base_mva)


def damping(d: ArrayLike, S: ArrayLike, *, base_mva: float, f_hz: float) -> np.ndarray:
    """``D = d S / (omega_s S_base)`` (p.u. power per rad/s), ``d`` in p.u. power per p.u. frequency."""
    return np.asarray(d, dtype=float) * np.asarray(S, dtype=float) / (2 * np.pi * f_hz * base_mva)


def tie_line_graph(area_buses: list[np.ndarray], bus: np.ndarray, f: np.ndarray, t: np.ndarray) -> list[tuple[int, int]]:
    """The area graph: 1-based area pairs ``(a, b)``, ``a < b``, joined by a branch.

    ``area_buses[a]``: the (increasing) bus numbers of area ``a``'s generators, the areas in
    bus order; every bus number in ``bus`` belongs to the area whose generator range is
    nearest (the cut between two consecutive areas midway between the last generator bus of
    one and the first of the next); ``f``, ``t``: the branches' end positions into ``bus``.
    """
    cuts = np.array([(area_buses[a][-1] + area_buses[a + 1][0]) / 2 for a in range(len(area_buses) - 1)])
    area = np.searchsorted(cuts, np.asarray(bus, dtype=float))
    pairs = {(int(min(area[i], area[j])) + 1, int(max(area[i], area[j])) + 1)
             for i, j in zip(np.asarray(f, dtype=int), np.asarray(t, dtype=int)) if area[i] != area[j]}
    return sorted(pairs)
