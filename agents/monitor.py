"""The monitor role: error norms of every agent against the true state, per round.

For each round ``k``, agent ``i`` and state block ``b`` (``"x"`` is the whole state):

* ``error_2 = |x_hat_i[k]_b - x[k]_b|_2``, ``error_inf`` likewise;
* ``relative_error_2 = error_2 / |x[k]_b|_2`` -- the metric for unstable plants, whose
  absolute error in float64 has a floor of about 1e-15 |x|.

A block is either 1-D state indices (``x_b = x[idx]``) or a 2-D matrix ``M`` of shape
``(r, n)``, a block over transformed coordinates (``x_b = M x``): its metrics are those of
``M (x_hat - x)`` and ``|M x|``. Plant models provide such blocks (``PlantModel.blocks``)
for errors in the plant's own units, e.g. the inverter line's squared voltages.

A round in which an agent published nothing (crashed, not yet joined) is NaN.

Estimator diagnostics (optional, any algorithm): an estimator may expose
``diagnostics() -> dict[str, float]`` (a flat mapping, e.g. an attack indicator) and a
``flagged`` bool property (it believes it detected an attack). A driver reads them after
each round with :func:`read_diagnostics` and hands them to
:meth:`Monitor.record_diagnostics`; they end up in ``diagnostics.parquet`` and in
``summary.json`` (``diagnostics``, ``detected_attacks``). Estimators without them cost
nothing.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from estimation.base import Diagnostics, Flags

if TYPE_CHECKING:  # an agent process reads diagnostics without the scenario layer
    from scenarios.build import Experiment

METRICS = ("error_2", "error_inf", "relative_error_2")


#: ``on_chunk(rows (c,), x (c, n), estimates (c, N, n))``: a flushed chunk of rounds
ChunkHook = Callable[[np.ndarray, np.ndarray, np.ndarray], None]


def plot_rows(exp: Experiment) -> list[tuple[str, np.ndarray, list[int]]]:
    """``[[output.plots]]`` as ``(name, row (n,), agent ids)``; default: ``x1`` and agent 1."""
    out = []
    for p in exp.scenario.output.plots:
        row = np.zeros(exp.n)
        for idx, w in zip(p.states, p.weights or [1.0] * len(p.states)):
            if not 1 <= idx <= exp.n:
                continue
            row[idx - 1] += w
        out.append((p.name, row, [a for a in (p.agents or [exp.agent_ids[0]]) if a in exp.agent_ids]))
    if not out:
        row = np.zeros(exp.n)
        row[0] = 1.0
        out.append(("x1", row, [exp.agent_ids[0]]))
    return out


def has_diagnostics(estimator: Any) -> bool:
    """Whether ``estimator`` declares :class:`~estimation.base.Diagnostics` or
    :class:`~estimation.base.Flags` (see the module docstring)."""
    return isinstance(estimator, (Diagnostics, Flags))


def read_diagnostics(estimator: Any) -> tuple[dict[str, float] | None, bool | None]:
    """``(diagnostics, flagged)`` of ``estimator`` now; ``None`` for what it does not expose."""
    diag = {str(k): float(v) for k, v in estimator.diagnostics().items()} if isinstance(estimator, Diagnostics) else None
    flag = bool(estimator.flagged) if isinstance(estimator, Flags) else None
    return diag, flag


class Monitor:
    """Collects per-round errors into dense arrays ``(rounds, agents, blocks)``
    (``error_2``, ``error_inf``; ``relative_error_2`` is derived from ``error_2`` and
    ``truth_norm`` when read).

    Estimates are buffered for a chunk of rounds (at most ~64 MB) and the norms computed
    for the whole chunk at once, which keeps the per-round cost of the monitor small.
    """

    CHUNK_BYTES = 64 * 2**20
    SLICE_BYTES = 4 * 2**20

    def __init__(self, exp: Experiment) -> None:
        self.exp = exp
        K = exp.n_rounds + 1
        self.block_names = list(exp.blocks)
        self._blocks = [np.asarray(exp.blocks[b]) for b in self.block_names]
        self._maps = [idx.astype(float) if idx.ndim == 2 else None for idx in self._blocks]
        for name, M in zip(self.block_names, self._maps):
            if M is not None and M.shape[1] != exp.n:
                raise ValueError(f"block {name!r}: a matrix block needs {exp.n} columns, got shape {M.shape}")
        self._whole = [M is None and len(idx) == exp.n for idx, M in zip(self._blocks, self._maps)]
        shape = (K, exp.N, len(self._blocks))
        self.error_2 = np.full(shape, np.nan)
        self.error_inf = np.full(shape, np.nan)
        self.truth_norm = np.full((K, len(self._blocks)), np.nan)
        self.last_round = -1
        self._chunk = max(1, min(1024, K, self.CHUNK_BYTES // max(1, exp.N * exp.n * 8)))
        # a chunk of one round (a large team) is not buffered: record() computes it at once
        self._est = np.full((self._chunk, exp.N, exp.n), np.nan) if self._chunk > 1 else None
        self._x = np.zeros((self._chunk, exp.n))
        self._rows: list[int] = []
        #: called as ``on_chunk(rows, x (c, n), estimates (c, N, n))`` after each flush;
        #: while it is set, rounds are flushed at least every ``flush_interval`` seconds
        #: (a recorder streaming them to disk loses at most that much, :mod:`agents.recorder`)
        self.on_chunk: ChunkHook | None = None
        self.flush_interval = 1.0
        self._flushed_at = -float("inf")  # the first round is handed on at once
        # [[output.plots]]: linear combinations of the state, truth and chosen agents
        self.plots = plot_rows(exp)
        self.traces = {name: np.full((K, 1 + len(agents)), np.nan) for name, _, agents in self.plots}
        #: estimator diagnostics: name -> (rounds, agents), NaN where not reported
        self.diagnostics: dict[str, np.ndarray] = {}
        #: (rounds, agents): 1.0 flagged, 0.0 not, NaN not reported; None until one is
        self.flags: np.ndarray | None = None

    def record_diagnostics(self, k: int, i: int, values: Mapping[str, float] | None,
                           flagged: bool | None = None) -> None:
        """Record agent index ``i``'s diagnostics and attack flag of round ``k``
        (see the module docstring; :func:`read_diagnostics` reads them off an estimator)."""
        self.record_diagnostic_rows(k, [i], values or {}, None if flagged is None else np.array([bool(flagged)]))

    def record_diagnostic_rows(self, k: int, agents: Sequence[int] | np.ndarray, values: Mapping[str, np.ndarray | float],
                               flagged: np.ndarray | None = None) -> None:
        """:meth:`record_diagnostics` of several agents at once: ``values`` name -> ``(M,)``
        (one per agent index in ``agents``), ``flagged`` ``(M,)`` bool or None."""
        K = self.error_2.shape[0]
        for name, v in values.items():
            arr = self.diagnostics.get(name)
            if arr is None:
                arr = self.diagnostics[name] = np.full((K, self.exp.N), np.nan)
            arr[k, agents] = v
        if flagged is not None:
            if self.flags is None:
                self.flags = np.full((K, self.exp.N), np.nan)
            self.flags[k, agents] = flagged

    def record(self, k: int, x: np.ndarray, estimates: np.ndarray, present: np.ndarray | None = None) -> None:
        """Record round ``k``: ``x`` (n,), ``estimates`` (N, n); ``present`` (N,) bool mask
        (absent agents are NaN)."""
        self.last_round = max(self.last_round, k)
        if self._est is None:  # one round per chunk: its norms now, from the caller's array
            self._flushed_at = time.monotonic()
            est = estimates if present is None else np.where(present[:, None], estimates, np.nan)
            self._compute(np.array([k]), np.asarray(x, dtype=float)[None], est[None])
            return
        r = len(self._rows)
        self._est[r] = estimates
        if present is not None:
            self._est[r, ~present] = np.nan
        self._x[r] = x
        self._rows.append(k)
        if len(self._rows) == self._chunk or (
                self.on_chunk is not None and time.monotonic() - self._flushed_at >= self.flush_interval):
            self.flush()

    def flush(self) -> None:
        """Compute the norms of the buffered rounds."""
        self._flushed_at = time.monotonic()
        if not self._rows or self._est is None:
            return
        c = len(self._rows)
        self._compute(np.array(self._rows), self._x[:c], self._est[:c])
        self._est[:c] = np.nan
        self._rows.clear()

    def _compute(self, rows: np.ndarray, xs: np.ndarray, ests: np.ndarray) -> None:
        """The norms of rounds ``rows``: true states ``xs`` (c, n), estimates ``ests`` (c, N, n).

        The errors are formed for a slice of agents at a time (at most ``SLICE_BYTES``: a
        large team's ``(c, N, n)`` error array would be as large as the estimates); every
        agent's norms are the same operations on the same values whatever the slice."""
        c, N = xs.shape[0], ests.shape[1]
        xbs = []
        for b, idx in enumerate(self._blocks):
            M = self._maps[b]
            xb = xs @ M.T if M is not None else xs if self._whole[b] else xs[:, idx]
            xn = np.sqrt(np.einsum("kj,kj->k", xb, xb))
            self.truth_norm[rows, b] = xn
            xbs.append(xn)
        step = max(1, self.SLICE_BYTES // max(1, c * xs.shape[1] * 8))
        for a0 in range(0, N, step):
            agents = slice(a0, min(N, a0 + step))
            E = ests[:, agents] - xs[:, None, :]
            for b, idx in enumerate(self._blocks):
                M = self._maps[b]
                if M is not None:
                    Eb = E @ M.T
                else:
                    Eb = E if self._whole[b] else E[:, :, idx]
                e2 = np.sqrt(np.einsum("kij,kij->ki", Eb, Eb))
                with np.errstate(invalid="ignore"):
                    einf = np.max(np.abs(Eb), axis=2)
                self.error_2[rows, agents, b] = e2
                self.error_inf[rows, agents, b] = einf
        for name, row, agents_of in self.plots:
            tr = self.traces[name]
            tr[rows, 0] = xs @ row
            tr[rows, 1:] = ests[:, [self.exp.agent_ids.index(a) for a in agents_of]] @ row
        if self.on_chunk is not None:
            self.on_chunk(rows, xs, ests)

    @property
    def relative_error_2(self) -> np.ndarray:
        """``(rounds, agents, blocks)``: ``error_2 / |x_b|`` (0 where both are 0), computed
        from ``error_2`` and ``truth_norm`` when read (a new array; not stored: a large
        team's metric arrays are a large part of its memory)."""
        return self.relative_rows(slice(None))

    def relative_rows(self, rows: Any) -> np.ndarray:
        """:attr:`relative_error_2` of the rounds ``rows`` only (an index or slice)."""
        e2, xn = self.error_2[rows], self.truth_norm[rows][..., None, :]
        with np.errstate(divide="ignore", invalid="ignore"):
            rel = e2 / xn
        rel[(xn == 0) & (e2 == 0)] = 0.0
        return rel

    def current_worst(self) -> float:
        """Worst infinity-norm error of the last recorded round (for progress bars)."""
        if self._rows and self._est is not None:
            r = len(self._rows) - 1
            with np.errstate(invalid="ignore"):
                v = np.abs(self._est[r] - self._x[r])
            return _worst(v)
        return _worst(self.error_inf[self.last_round]) if self.last_round >= 0 else float("nan")

    def metric(self, name: str) -> np.ndarray:
        """``(rounds, agents, blocks)`` array of a metric; ``error_ratio`` is ``error_2``
        divided by the agent's ``error_2`` at round 0 (the decay of the initial error)."""
        self.flush()
        if name == "error_ratio":
            with np.errstate(divide="ignore", invalid="ignore"):
                return self.error_2 / self.error_2[:1]
        if name == "relative_error_2":
            return self.relative_error_2
        return {"error_2": self.error_2, "error_inf": self.error_inf}[name]


def _worst(v: np.ndarray) -> float:
    """The largest value of ``v`` that is not NaN (NaN when none is: a round of no report)."""
    return float(np.nanmax(v)) if not np.all(np.isnan(v)) else float("nan")
