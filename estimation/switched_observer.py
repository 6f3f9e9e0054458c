"""Switched partial observers for agents on periodic patrols (Mitra et al. 2019, Sec. 3).

In modal coordinates (eq. (4), :mod:`estimation.modal`) location ``r`` measures
``y^(r) = C~^(r) z`` with ``C~^(r) = C^(r) V``. Its partial observer tracks
``v^(r)``, the modes whose column of ``C~^(r)`` is non-zero (for distinct eigenvalues
these are exactly the detectable ones, Section 3.1), ``J^(r) = diag`` of their
eigenvalues. Agent ``i`` runs, for every location of its patrol, eqs. (7)-(8)::

    v_hat[k+1] = (J - L C~) v_hat[k] + L y^(r)[k]   if sigma_i[k] = r      (visiting)
    v_hat[k+1] = J v_hat[k]                            otherwise             (open loop)

Sampled once per period the error obeys ``M = (J - L C~) J^(T-1)`` (eqs. (10)-(11)).

Gain design (the paper only states that a stabilising ``L`` exists): with
``d = lambda^T`` and ``c = C~ J^(T-1)``, ``M = diag(d) - L c``. A mode whose open-loop
``|lambda^T|`` is already below ``target`` is left alone (``L`` has a zero row for it, so
``M`` is block triangular and that eigenvalue stays ``lambda^T``); forcing such fast
stable modes to the target needs enormous gains (``~1e6`` for the 4-cell plant). The
other ("moved") modes get distinct poles in ``(target / 2, target]``
(:func:`target_poles`), or 0 with ``deadbeat=True``. A location
with several output rows uses the single combined output ``w^T y`` (``w`` = ones, or a
fixed pseudo-random vector if ones cancels a column). For a diagonal ``diag(d_S)`` and
a row ``c_S`` with no zero entry, the gain placing the characteristic polynomial
``p(z) = prod (z - pole)`` is explicit (partial fractions of ``det(zI - D + l c)``)::

    l_q = p(d_q) / (c_q prod_{s != q} (d_q - d_s)),

which needs the moved ``d_q = lambda_q^T`` distinct (Lemma 1: true for odd ``T``, or for
eigenvalues of distinct magnitude); a :class:`DesignError` names the location otherwise.
Repeated target poles give a Jordan block (no problem for a design that is only required
to be Schur).

Measured on the plants of Section 8 (seed 0, periods 13/14/14/14): for ``cells`` the
default target 0.5 needs gains below 4 (at most 2 modes per location); for ``diffusion``
every location sees all 10 modes of its cell and up to 8 of them must move, with sampled
eigenvalues clustered in ``[0.5, 1]``, so target 0.5 needs gains ~5e4 and a local error
is still ~1.5e-3 of its initial value after 300 rounds, while ``deadbeat=True`` reaches
~4e-6 (with a transient peak ~3e5 times the initial error). Prefer ``deadbeat`` there.

Source sets (Definition 1): ``S_j`` = agents whose patrol has a location observing mode
``j``. When several locations of one patrol observe the same mode (Remark 4), the agent's
estimate of that mode is taken from the first location in patrol order that observes it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from .errors import DesignError
from .modal import ModalForm
from .patrols import Patrol

#: relative size below which a modal measurement column counts as zero
COLUMN_TOL = 1e-9


def observed_modes(C_tilde: np.ndarray, *, tol: float = COLUMN_TOL) -> np.ndarray:
    """Modes (column indices) with a non-zero column in ``C~`` ``(r, n)``."""
    C_tilde = np.atleast_2d(np.asarray(C_tilde, dtype=float))
    norms = np.linalg.norm(C_tilde, axis=0)
    scale = float(np.max(norms)) if norms.size else 0.0
    return np.flatnonzero(norms > tol * max(scale, 1e-300)) if scale > 0 else np.zeros(0, dtype=int)


def sampled_error_matrix(lam: np.ndarray, C_tilde: np.ndarray, L: np.ndarray, period: int) -> np.ndarray:
    """``M = (J - L C~) J^(T-1)``, eq. (11); ``lam (s,)``, ``C_tilde (r, s)``, ``L (s, r)``."""
    lam = np.asarray(lam, dtype=float)
    return (np.diag(lam) - L @ C_tilde) * lam ** (period - 1)


def _combiner(c: np.ndarray) -> np.ndarray:
    """Output combination ``w (r,)`` keeping every column of ``c (r, s)`` non-zero."""
    r = c.shape[0]
    cands = [np.ones(r)] + list(np.random.default_rng(12345).standard_normal((8, r)))
    best, score = cands[0], -1.0
    for w in cands:
        comb = w @ c
        s = float(np.min(np.abs(comb)) / max(np.max(np.abs(c)), 1e-300)) if comb.size else 1.0
        if s > score:
            best, score = w, s
        if s > 1e-3:
            return w
    return best


def sampled_gain(
    lam: np.ndarray,
    C_tilde: np.ndarray,
    period: int,
    *,
    target: float = 0.5,
    deadbeat: bool = False,
    where: str = "location",
) -> tuple[np.ndarray, np.ndarray]:
    """Gain ``L`` making the sampled error matrix (11) Schur.

    Parameters
    ----------
    lam : (s,) array  eigenvalues of the location's observed modes (``J``)
    C_tilde : (r, s) array  the location's modal measurement rows, every column non-zero
    period : int >= 1  ``T`` of the visits
    target : float in [0, 1)
        Modes with ``|lambda^T| >= target`` are moved to the poles
        :func:`target_poles` (at most ``target``); the others are left alone.
    deadbeat : bool
        Move the moved modes to 0 instead of ``target``.
    where : str  names the location in error messages

    Returns
    -------
    L : (s, r) array
    moved : (s,) bool array  the modes whose pole was placed
    """
    lam = np.asarray(lam, dtype=float)
    C_tilde = np.atleast_2d(np.asarray(C_tilde, dtype=float))
    s, r = lam.shape[0], C_tilde.shape[0]
    if C_tilde.shape[1] != s:
        raise DesignError(f"{where}: C~ has {C_tilde.shape[1]} columns for {s} modes")
    if not (0.0 <= target < 1.0):
        raise DesignError(f"{where}: pole target must be in [0, 1), got {target}")
    if period < 1:
        raise DesignError(f"{where}: period must be >= 1, got {period}")
    d = lam**period
    moved = np.abs(d) >= target
    L = np.zeros((s, r))
    if not np.any(moved):
        return L, moved
    w = _combiner(C_tilde)
    c = (w @ C_tilde) * lam ** (period - 1)
    S = np.flatnonzero(moved)
    dS, cS = d[S], c[S]
    scale = max(1.0, float(np.max(np.abs(dS))))
    if np.any(np.abs(cS) <= COLUMN_TOL * max(float(np.max(np.abs(c))), 1e-300)):
        raise DesignError(f"{where}: a mode to be moved is not seen by the combined output")
    diff = dS[:, None] - dS[None, :]
    np.fill_diagonal(diff, 1.0)
    if S.size > 1 and np.min(np.abs(diff)) <= 1e-12 * scale:
        a, b = np.unravel_index(np.argmin(np.abs(diff)), diff.shape)
        raise DesignError(
            f"{where}: modes with lambda {lam[S[a]]:.6g} and {lam[S[b]]:.6g} have equal lambda^T "
            f"at period {period} (Lemma 1: use an odd period); the sampled pair is not detectable"
        )
    poles = target_poles(S.size, target=target, deadbeat=deadbeat)
    p_at_d = np.prod(dS[:, None] - poles[None, :], axis=1)  # p(d_q), p(z) = prod (z - pole)
    lS = p_at_d / (cS * np.prod(diff, axis=1))
    L[S] = np.outer(lS, w)
    return L, moved


def target_poles(s: int, *, target: float, deadbeat: bool = False) -> np.ndarray:
    """The ``s`` sampled poles given to moved modes: ``target * (1 - q / (2 s))``, ``q = 0..s-1``.

    Distinct poles in ``(target / 2, target]`` keep ``M`` diagonalisable, so its computed
    spectral radius is ``target`` to rounding (a repeated pole gives a Jordan block whose
    computed eigenvalues scatter by ``eps^(1/s)``). ``deadbeat``: all poles at 0 (``M``
    nilpotent on the moved modes).
    """
    if deadbeat:
        return np.zeros(s)
    return target * (1.0 - np.arange(s) / (2.0 * s))


@dataclass(frozen=True, eq=False)
class LocationObserver:
    """One partial observer (7)-(8) of one agent at one location.

    Attributes
    ----------
    location : int
    modes : (s,) int array  global modes of ``v^(r)``
    lam : (s,) array;  C : (r, s) array ``C~^(r)`` on those modes;  L : (s, r) array
    period : int  ``T`` of the agent's visits to this location
    F : (s, s) array  ``J - L C~`` (eq. (8), visiting)
    M : (s, s) array  sampled error matrix (11)
    moved : (s,) bool array  modes whose sampled pole was placed
    """

    location: int
    modes: np.ndarray
    lam: np.ndarray
    C: np.ndarray
    L: np.ndarray
    period: int
    F: np.ndarray
    M: np.ndarray
    moved: np.ndarray

    @property
    def sampled_radius(self) -> float:
        """Spectral radius of ``M`` (< 1: the periodically sampled error (10) is stable)."""
        return float(np.max(np.abs(np.linalg.eigvals(self.M)))) if self.M.size else 0.0


@dataclass(frozen=True, eq=False)
class AgentObservers:
    """All partial observers of one agent, laid out in one flat vector.

    Attributes
    ----------
    agent : int
    patrol : Patrol
    observers : tuple of LocationObserver, in patrol order
    slices : tuple of slice  each observer's part of the flat partial estimate
    lam_flat : (s_tot,) array  eigenvalue of every flat entry (open-loop update)
    observed : (o,) int array  modes observed by the patrol (``O_i``), sorted
    owner : (o,) int array  flat index whose estimate is used for each observed mode
    by_location : dict  location -> index into ``observers``
    """

    agent: int
    patrol: Patrol
    observers: tuple[LocationObserver, ...]
    slices: tuple[slice, ...]
    lam_flat: np.ndarray
    observed: np.ndarray
    owner: np.ndarray
    by_location: dict

    @property
    def size(self) -> int:
        return int(self.lam_flat.shape[0])


def design_agent_observers(
    modal: ModalForm,
    loc_C: Sequence[np.ndarray],
    patrol: Patrol,
    *,
    agent: int,
    target: float = 0.5,
    deadbeat: bool = False,
) -> AgentObservers:
    """Partial observers and gains (Proposition 1) for one agent's patrol.

    Parameters
    ----------
    modal : ModalForm
    loc_C : sequence of (r_l, n) arrays  measurement rows of every location (eq. (2))
    patrol : Patrol
    agent : int  for error messages
    target, deadbeat : see :func:`sampled_gain`
    """
    obs, slices, lam_parts = [], [], []
    owner: dict[int, int] = {}
    start = 0
    for loc, per in zip(patrol.locations, patrol.periods):
        if loc >= len(loc_C):
            raise DesignError(f"agent {agent}: patrol location {loc} does not exist ({len(loc_C)} locations)")
        Ct = modal.modal_rows(loc_C[loc])
        modes = observed_modes(Ct)
        lam, C = modal.lam[modes], Ct[:, modes]
        L, moved = sampled_gain(lam, C, per, target=target, deadbeat=deadbeat, where=f"agent {agent}, location {loc}")
        F = np.diag(lam) - L @ C
        M = sampled_error_matrix(lam, C, L, per)
        for a in (modes, lam, C, L, F, M, moved):
            a.setflags(write=False)
        obs.append(LocationObserver(loc, modes, lam, C, L, per, F, M, moved))
        slices.append(slice(start, start + modes.size))
        lam_parts.append(lam)
        for q, j in enumerate(modes):
            owner.setdefault(int(j), start + q)
        start += modes.size
    observed = np.array(sorted(owner), dtype=int)
    lam_flat = np.concatenate(lam_parts) if lam_parts else np.zeros(0)
    own = np.array([owner[int(j)] for j in observed], dtype=int)
    for a in (observed, lam_flat, own):
        a.setflags(write=False)
    by_loc = {o.location: q for q, o in enumerate(obs)}
    return AgentObservers(agent, patrol, tuple(obs), tuple(slices), lam_flat, observed, own, by_loc)


def source_sets(agents: Sequence[AgentObservers], n_modes: int) -> tuple[frozenset[int], ...]:
    """``S_j`` of Definition 1 for every mode ``j``: agents whose patrol observes it."""
    S: list[set[int]] = [set() for _ in range(n_modes)]
    for a in agents:
        for j in a.observed:
            S[int(j)].add(a.agent)
    return tuple(frozenset(s) for s in S)


def observer_step(
    v: np.ndarray,
    design: AgentObservers,
    location: int | None,
    y: np.ndarray | None,
) -> np.ndarray:
    """One round of eqs. (7)-(8) for all of an agent's partial observers.

    Parameters
    ----------
    v : (..., s_tot) array  flat partial estimates ``v_hat[k]`` (leading batch axes allowed)
    design : AgentObservers
    location : int or None  ``sigma_i[k]``
    y : (r,) array or None  the measurement ``y^(sigma_i[k])[k]`` (None: missing, open loop)

    Returns
    -------
    (..., s_tot) array  ``v_hat[k+1]`` (a new array)
    """
    out = v * design.lam_flat
    if location is not None and y is not None:
        q = design.by_location.get(location)
        if q is not None:
            ob, sl = design.observers[q], design.slices[q]
            out[..., sl] = v[..., sl] @ ob.F.T + ob.L @ np.asarray(y, dtype=float)
    return out
