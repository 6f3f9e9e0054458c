"""LFRE, SW-LFRE and their variants for mobile agents (Mitra et al. 2019, Sections 5-7).

Every agent ``i`` keeps a modal estimate ``z_hat_i`` (eq. (4); ``x_hat_i = V z_hat_i``),
one scalar per mode:

* modes its patrol observes (``O_i``): the switched partial observers (7)-(8)
  (:mod:`estimation.switched_observer`);
* modes it does not observe ("fused" modes, ``UO_i``): fusion of its MEDAG in-neighbours'
  estimates ``N_i^(j)`` (:mod:`estimation.robustness`) by one of

  - **LFRE** (Section 7.1, memoryless): if at least ``2f + 1`` of ``N_i^(j)`` delivered a
    fresh estimate, ``z_hat[k+1] = lambda * trimmed_mean`` (21); otherwise open loop
    ``z_hat[k+1] = lambda z_hat[k]`` (22);
  - **SW-LFRE** (Section 5): the newest estimate of every neighbour, delay-compensated
    ``zbar_il = lambda^tau_il z_hat_l[k - tau_il]`` (0 before the first one), then
    ``z_hat[k+1] = lambda * trimmed_mean(zbar)`` (14);
  - ``fusion="median"``: the median instead of the trimmed mean (Remark 7);
  - ``fusion="average"``: the plain average of the neighbours (non-resilient baseline,
    Fig. 13); trimming and the ``2f + 1`` minimum are dropped.

  Uniform weights over the kept values (the paper allows any convex weights).
* modes that are stable, unobserved and not fused run open loop.

Stable unobserved modes are fused too by default (``fuse_stable=True``): the paper only
needs ``Omega_U`` (``|lambda| >= 1``), but open loop lets an error in a slow stable mode
(``lambda ~ 0.99`` in the diffusion cells) decay for hundreds of rounds. A stable mode
without a MEDAG falls back to open loop.

Round convention (:mod:`estimation.base`). ``step(k, y, inbox)`` returns ``z_hat[k]``:

* the measurement taken in round ``k`` (at the location ``sigma_i[k]`` of the patrol)
  is stored and enters in round ``k + 1``, exactly as ``y[k]`` drives ``v_hat[k+1]`` in
  eq. (7); so ``z_hat[k]`` uses measurements up to ``k - 1``;
* a neighbour's message stamped ``phi`` carries ``z_hat_l[phi]``; for the update to
  round ``k`` the paper's "time-step k" is our ``k - 1``: LFRE uses only messages stamped
  exactly ``k - 1`` (a fresh packet), SW-LFRE compensates each by
  ``lambda^((k - 1) - phi)``. A stamp later than ``k - 1`` cannot be genuine: LFRE ignores
  it, SW-LFRE treats it as ``k - 1`` (after trimming any value an adversary supplies is
  harmless, Remark 8). SW-LFRE remembers the newest message per neighbour itself, so
  an inbox holding only this round's deliveries works as well as a persistent one.
* a skipped round (``k > k_prev + 1``) advances the observers open loop.

The outgoing payload is the modal estimate ``z_hat[k]`` of shape ``(n,)`` (neighbours
fuse modal coordinates; converting to ``x`` and back would cost ``O(n^2)`` per message).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from .base import EstimatePayload, Inbox, MaskedInputs
from .batching import Batch, Batchable
from .errors import DesignError
from .lfre_batch import FusionBatch
from .modal import ModalForm, modal_form
from .patrols import Patrol, PatrolSchedule
from .robustness import Medag, build_medag
from .switched_observer import AgentObservers, design_agent_observers, observer_step, source_sets
from .trimmed_mean import FUSIONS, fuse


@dataclass(frozen=True, eq=False)
class MitraDesign:
    """Offline design for a team (built once per scenario by :func:`design`).

    Attributes
    ----------
    modal : ModalForm
    loc_C : tuple of (r_l, n) arrays  measurement rows per location
    agents : tuple of AgentObservers  per agent
    schedules : tuple of PatrolSchedule  per agent (location lookups)
    sources : tuple of frozenset  ``S_j`` per mode
    medags : dict  mode -> Medag, for every mode some agent fuses
    fused : tuple of (F_i,) int arrays  per agent, the modes it fuses
    f : int;  r : int  (MEDAG in-degree, ``2f + 1`` or ``m f + 1``)
    Adj : (N, N) int array  baseline graph
    """

    modal: ModalForm
    loc_C: tuple[np.ndarray, ...]
    agents: tuple[AgentObservers, ...]
    schedules: tuple[PatrolSchedule, ...]
    sources: tuple[frozenset[int], ...]
    medags: dict
    fused: tuple[np.ndarray, ...]
    f: int
    r: int
    Adj: np.ndarray

    @property
    def n(self) -> int:
        return self.modal.n

    def mode_label(self, j: int, block_names: Sequence[str] | None = None) -> str:
        b = int(self.modal.block_of_mode[j])
        name = block_names[b] if block_names is not None else f"block {b}"
        return f"mode {j} ({name}, lambda={self.modal.lam[j]:.6g})"


def design(
    A: np.ndarray,
    loc_C: Sequence[np.ndarray],
    patrols: Sequence[Patrol],
    Adj: np.ndarray,
    *,
    f: int,
    r: int | None = None,
    target: float = 0.5,
    deadbeat: bool = False,
    fuse_stable: bool = True,
    blocks: Sequence[Sequence[int] | np.ndarray] | None = None,
    block_names: Sequence[str] | None = None,
) -> MitraDesign:
    """Modal form, observers, source sets and MEDAGs for a team of patrolling agents.

    Parameters
    ----------
    A : (n, n) array;  loc_C : sequence of (r_l, n) arrays, one per location
    patrols : sequence of Patrol, one per agent (agent ``i`` = index ``i``)
    Adj : (N, N) array  baseline graph, ``Adj[i, l] = 1``: ``i`` receives from ``l``
    f : int  attack budget;  r : int, MEDAG in-degree (default ``2f + 1``)
    target, deadbeat : observer poles (:func:`~estimation.switched_observer.sampled_gain`)
    fuse_stable : bool  also fuse stable unobserved modes (see the module docstring)
    blocks, block_names : decoupled blocks of ``A`` and their names (error messages)

    Raises
    ------
    DesignError
        Assumption 1 fails in a block, a gain cannot be designed, an unstable or marginal
        mode is observed by no patrol, or a mode that must be fused has no MEDAG (the
        message names the mode and the agents that cannot be reached).
    """
    modal = modal_form(A, blocks=blocks)
    Adj = np.asarray(Adj)
    N = len(patrols)
    if Adj.shape != (N, N):
        raise DesignError(f"baseline graph has shape {Adj.shape} for {N} agents")
    loc_C = tuple(np.atleast_2d(np.asarray(C, dtype=float)) for C in loc_C)
    for l, C in enumerate(loc_C):
        if C.shape[1] != modal.n:
            raise DesignError(f"location {l}: measurement rows have {C.shape[1]} columns, A has {modal.n}")
    agents = tuple(
        design_agent_observers(modal, loc_C, p, agent=i, target=target, deadbeat=deadbeat) for i, p in enumerate(patrols)
    )
    S = source_sets(agents, modal.n)
    r_used = 2 * f + 1 if r is None else int(r)
    cache: dict[frozenset, Medag | DesignError] = {}
    medags: dict[int, Medag] = {}
    fused: list[list[int]] = [[] for _ in range(N)]
    tmp = MitraDesign(modal, loc_C, agents, (), S, {}, (), f, r_used, Adj)
    for j in range(modal.n):
        outsiders = [i for i in range(N) if i not in S[j]]
        unstable = abs(modal.lam[j]) >= 1.0
        if not outsiders or not (unstable or fuse_stable):
            continue
        label = tmp.mode_label(j, block_names)
        if not S[j]:
            if unstable:
                raise DesignError(f"{label}: no agent's patrol observes this mode (|lambda| >= 1): not detectable")
            continue
        if S[j] not in cache:
            try:
                cache[S[j]] = build_medag(Adj, S[j], f=f, r=r_used, mode=j, label=label)
            except DesignError as exc:
                cache[S[j]] = exc
        got = cache[S[j]]
        if isinstance(got, DesignError):
            if unstable:
                msg = str(got)
                raise DesignError(label + msg[msg.index(": no MEDAG") :]) from got
            continue
        medags[j] = got
        for i in outsiders:
            fused[i].append(j)
    schedules = tuple(PatrolSchedule(p) for p in patrols)
    fz = tuple(np.array(v, dtype=int) for v in fused)
    for a in fz:
        a.setflags(write=False)
    return MitraDesign(modal, loc_C, agents, schedules, S, medags, fz, f, r_used, Adj)


# ---------------------------------------------------------------- pure per-round maths


def compensate(values: np.ndarray, stamps: np.ndarray, *, k: int, lam: np.ndarray) -> np.ndarray:
    """SW-LFRE step 1: ``zbar = lambda^((k-1) - phi) z_hat_l[phi]`` for the update to round ``k``.

    Parameters
    ----------
    values : (..., F, d) array  neighbours' estimates of ``F`` modes (column per neighbour)
    stamps : (..., d) int array  their stamps ``phi`` (clipped to ``<= k - 1``)
    lam : (F,) array
    """
    delay = np.maximum((k - 1) - np.asarray(stamps), 0)
    with np.errstate(over="ignore", invalid="ignore"):
        return values * np.asarray(lam)[:, None] ** delay[..., None, :]


def lfre_update(z_prev: np.ndarray, fused: np.ndarray, lam: np.ndarray, *, gap: int = 1) -> np.ndarray:
    """Eqs. (21)-(22): ``lambda * fused`` where available, else ``lambda^gap * z_prev`` (open loop)."""
    hold = (lam if gap == 1 else lam**gap) * z_prev
    return np.where(np.isnan(fused), hold, lam * fused)


# ------------------------------------------------------------------------- estimators


class _ModalFusion(Batchable, MaskedInputs, EstimatePayload):
    """Shared state and round logic of :class:`LFRE` and :class:`SWLFRE`.

    Batchable: agents with the same fusion rule and ``f`` are stepped together by
    :class:`FusionBatch` (their own :meth:`begin` / :meth:`finish` around one
    :func:`~estimation.trimmed_mean.fuse_blocks` call: bit-identical to :meth:`step`)."""

    _sliding = False

    def __init__(self, des: MitraDesign, *, agent: int, fusion: str = "trimmed", z0: np.ndarray | None = None) -> None:
        if fusion not in FUSIONS:
            raise DesignError(f"unknown fusion {fusion!r}; expected one of {', '.join(FUSIONS)}")
        if not 0 <= agent < len(des.agents):
            raise DesignError(f"agent {agent} outside 0..{len(des.agents) - 1}")
        self.design, self.agent, self.fusion, self.f = des, agent, fusion, des.f
        n = des.n
        self._shape = (n,)
        self._obs = des.agents[agent]
        self._sched = des.schedules[agent]
        self._lam = des.modal.lam
        # the fused modes F and, per mode, which neighbours are in its MEDAG N_i^(j):
        # member[a, c] <=> neighbour nb[c] feeds mode F[a] (every mode fused in one call)
        F = [int(j) for j in des.fused[agent]]
        groups: dict[tuple[int, ...], list[int]] = {}  # modes by MEDAG neighbour set
        for a, j in enumerate(F):
            groups.setdefault(des.medags[j].neighbours[agent], []).append(a)
        nb = sorted({l for key in groups for l in key})
        self._nb = np.array(nb, dtype=int)
        self._col = {l: c for c, l in enumerate(nb)}
        self._F = np.asarray(des.fused[agent], dtype=np.intp)  # the design's read-only array (no copy per agent)
        member = np.zeros((len(F), len(nb)), dtype=bool)
        for key, rows in groups.items():
            member[np.ix_(rows, [self._col[l] for l in key])] = True
        self._member = member
        self._need = 1 if fusion == "average" else 2 * self.f + 1
        self._z = np.zeros(n) if z0 is None else np.array(z0, dtype=float).reshape(n)
        self._v = self._z[self._obs_modes_flat()].copy()
        self._k: int | None = None
        self._open: np.ndarray | None = None  # z_hat[k] before fusion, between begin and finish
        self._loc: int | None = None
        self._y: np.ndarray | None = None
        self.rejected = 0  # messages skipped for a wrong shape
        # the newest value of every neighbour: SW-LFRE's memory (LFRE is memoryless)
        self._mem_val = np.zeros((len(nb) if self._sliding else 0, self._F.size))
        self._mem_stamp = np.zeros(len(nb), dtype=np.int64)
        self._mem_has = np.zeros(len(nb), dtype=bool)

    def batch_key(self) -> tuple:
        return ("modal_fusion", self.fusion, self.f)

    @classmethod
    def batch(cls, members, **kw) -> Batch:
        return FusionBatch(members, **kw)

    def uses(self, sender: int) -> np.ndarray:
        """``(n,)`` 0/1 mask of the payload components (modes) for which this agent fuses
        ``sender``'s value (``sender`` in ``N_i^(j)`` of mode ``j``'s MEDAG). Read-only."""
        cache = self.__dict__.setdefault("_uses", {})
        mask = cache.get(sender)
        if mask is None:
            mask = np.zeros(self.design.n)
            for j in self._F:
                if sender in self.design.medags[int(j)].neighbours[self.agent]:
                    mask[j] = 1.0
            mask.flags.writeable = False
            cache[sender] = mask
        return mask

    def _obs_modes_flat(self) -> np.ndarray:
        return np.concatenate([o.modes for o in self._obs.observers]) if self._obs.observers else np.zeros(0, dtype=int)

    @property
    def estimate(self) -> np.ndarray:
        """``x_hat_i[k] = V z_hat_i[k]``, shape ``(n,)`` (a new array)."""
        eye = self.design.modal.is_identity
        return self._z.copy() if eye else self.design.modal.V @ self._z

    @property
    def payload_is_estimate(self) -> bool:
        """The payload ``z_hat`` is the estimate ``x_hat = V z_hat`` when ``V`` is the
        identity (a diagonal process: ``mitra_cells.toml``); :attr:`estimate` is then a
        copy of it."""
        return self.design.modal.is_identity

    @property
    def modal_estimate(self) -> np.ndarray:
        """``z_hat_i[k]``, shape ``(n,)`` (a copy)."""
        return self._z.copy()

    @property
    def partial_estimate(self) -> np.ndarray:
        """Flat partial-observer estimates ``v_hat`` of every location, ``(s_tot,)`` (a copy)."""
        return self._v.copy()

    def _valid(self, value: np.ndarray) -> bool:
        # finiteness is the codec's job; a NaN that gets here counts as a missing value
        ok = getattr(value, "shape", None) == self._shape
        if not ok:
            self.rejected += 1
        return ok

    def step(self, k: int, measurement: np.ndarray | None, inbox: Inbox) -> np.ndarray:
        """Advance to round ``k``; return the payload ``z_hat_i[k]`` ``(n,)`` stamped ``k``.

        The same as :meth:`begin`, :func:`~estimation.trimmed_mean.fuse` of what it
        returns, then :meth:`finish` (a batched driver fuses many agents in one call)."""
        values = self.begin(k, inbox)
        got = None if values is None else fuse(values, fusion=self.fusion, f=self.f)
        return self.finish(k, measurement, got)

    def begin(self, k: int, inbox: Inbox) -> np.ndarray | None:
        """First half of :meth:`step`: the observers (7)-(8) and the open-loop prediction.

        Returns the values to fuse, ``(F, d)``: row ``a`` holds mode ``F[a]``'s values
        from the ``d`` senders, NaN where a sender is missing or not in the mode's MEDAG;
        or None when there is nothing to fuse this round. Hand :func:`fuse` of it (or None)
        to :meth:`finish`."""
        self._open = None
        if self._k is not None:
            if k <= self._k:
                raise ValueError(f"agent {self.agent}: round {k} after round {self._k}; rounds must increase")
            gap = k - self._k
            v = observer_step(self._v, self._obs, self._loc, self._y)
            if gap > 1:
                v *= self._obs.lam_flat ** (gap - 1)
            self._v = v
            z = (self._lam if gap == 1 else self._lam**gap) * self._z
            z[self._obs.observed] = v[self._obs.owner]
            if not self._F.size:
                self._z = z
                return None
            self._open = z
            return self._fusion_input(k, inbox)
        if self._sliding:
            self._remember(k, inbox)
        return None

    def finish(self, k: int, measurement: np.ndarray | None, fused: np.ndarray | None) -> np.ndarray:
        """Second half of :meth:`step`: ``fused`` (the fusion of :meth:`begin`'s values,
        ``(F,)``, NaN where too few) enters ``z_hat[k]``; the measurement is stored."""
        z = self._open
        if z is not None:
            self._open = None
            if fused is not None:
                self._fusion_output(z, fused)
            self._z = z
        self._k = k
        self._take_measurement(k, measurement)
        self._z.flags.writeable = False  # the payload itself: never modified (the next round makes a new z)
        return self._z

    def _take_measurement(self, k: int, measurement: np.ndarray | None) -> None:
        loc = self._sched.location(k)
        if measurement is None:
            self._loc, self._y = loc, None
            return
        if loc is None:
            raise ValueError(f"agent {self.agent}: a measurement in round {k}, but its patrol is commuting")
        y = np.asarray(measurement, dtype=float).reshape(-1)
        rows = self.design.loc_C[loc].shape[0]
        if y.shape != (rows,):
            raise ValueError(f"agent {self.agent}: location {loc} gives {rows} value(s), got shape {np.shape(measurement)}")
        self._loc, self._y = loc, y.copy()

    def _fusion_input(self, k: int, inbox: Inbox) -> np.ndarray | None:
        raise NotImplementedError

    def _fusion_output(self, z: np.ndarray, got: np.ndarray) -> None:
        raise NotImplementedError

    def _gather(self, inbox: Inbox, *, stamp: int | None = None) -> tuple[list[int], list[int], list[np.ndarray]]:
        """Columns, stamps and values of the inbox messages from MEDAG neighbours
        (only those stamped ``stamp`` when given)."""
        cols, stamps, rows = [], [], []
        for rec in inbox.values():
            c = self._col.get(rec.sender)
            if c is None or (stamp is not None and rec.stamp != stamp) or not self._valid(rec.value):
                continue
            cols.append(c)
            stamps.append(rec.stamp)
            rows.append(rec.value)
        return cols, stamps, rows

    def _remember(self, k: int, inbox: Inbox) -> None:
        """Keep the newest message per neighbour (stamps later than ``k - 1`` read as ``k - 1``)."""
        cols, stamps, rows = self._gather(inbox)
        if not cols:
            return
        c = np.array(cols)
        st = np.minimum(np.array(stamps, dtype=np.int64), k - 1)
        newer = ~self._mem_has[c] | (st > self._mem_stamp[c])
        if newer.all():
            self._mem_val[c] = np.asarray(rows, dtype=float)[:, self._F]
        elif newer.any():
            self._mem_val[c[newer]] = np.asarray(rows, dtype=float)[newer][:, self._F]
        else:
            return
        self._mem_stamp[c[newer]] = st[newer]
        self._mem_has[c[newer]] = True


class LFRE(_ModalFusion):
    """LFRE over erasure channels, eqs. (21)-(22) (memoryless; Section 7.1).

    Parameters
    ----------
    des : MitraDesign
    agent : int  0-based
    fusion : {"trimmed", "median", "average"}  eq. (21), Remark 7, or the non-resilient
        baseline (average of the fresh neighbours' values; open loop if none)
    z0 : (n,) array, optional  initial modal estimate (default 0)
    """

    def _fusion_input(self, k: int, inbox: Inbox) -> np.ndarray | None:
        # the open loop (22) is already in z; fuse only messages stamped k - 1
        cols, _, rows = self._gather(inbox, stamp=k - 1)
        if len(rows) < self._need:
            return None
        vals = np.asarray(rows, dtype=float)[:, self._F].T  # (F, d) from the d fresh senders
        return np.where(self._member[:, cols], vals, np.nan)

    def _fusion_output(self, z: np.ndarray, got: np.ndarray) -> None:
        ok = ~np.isnan(got)  # at least 2f + 1 fresh MEDAG neighbours: eq. (21)
        Fok = self._F[ok]
        z[Fok] = self._lam[Fok] * got[ok]


class SWLFRE(_ModalFusion):
    """SW-LFRE with time stamps and ``lambda^tau`` delay compensation, eq. (14) (Section 5).

    Parameters as :class:`LFRE`; ``fusion="median"`` is Remark 7. Every MEDAG neighbour
    always contributes a value (0 before its first message, footnote 9), so the fused value
    always exists and there is no open-loop branch.
    """

    _sliding = True

    def _fusion_input(self, k: int, inbox: Inbox) -> np.ndarray:
        self._remember(k, inbox)
        delay = (k - 1) - self._mem_stamp
        block = self._mem_val  # (d, F): the newest value of every neighbour (0 before its first)
        if delay.max() > 0:  # step 1: zbar = lambda^tau z_hat_l[k - 1 - tau]
            with np.errstate(over="ignore", invalid="ignore"):
                block = block * self._lam[self._F] ** delay[:, None]
            if not np.all(np.isfinite(block)):
                block = np.nan_to_num(block, nan=0.0, posinf=np.inf, neginf=-np.inf)
        # every MEDAG neighbour contributes, so each mode has r >= 2f + 1 values
        return np.where(self._member, block.T, np.nan)

    def _fusion_output(self, z: np.ndarray, got: np.ndarray) -> None:
        z[self._F] = self._lam[self._F] * got  # eq. (14)


RULES = {"lfre": (LFRE, "trimmed"), "sw_lfre": (SWLFRE, "trimmed"), "median": (SWLFRE, "median"), "average": (LFRE, "average")}


def make_estimator(des: MitraDesign, *, agent: int, rule: str = "lfre", z0: np.ndarray | None = None) -> _ModalFusion:
    """Estimator by rule name: ``"lfre"`` (21)-(22), ``"sw_lfre"`` (14), ``"median"``
    (SW-LFRE with the median, Remark 7), ``"average"`` (non-resilient baseline, Fig. 13)."""
    if rule not in RULES:
        raise DesignError(f"unknown rule {rule!r}; expected one of {', '.join(RULES)}")
    cls, fusion = RULES[rule]
    return cls(des, agent=agent, fusion=fusion, z0=z0)
