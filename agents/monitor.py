"""The monitor role: error norms of every agent against the true state, per round.

For each round ``k``, agent ``i`` and state block ``b`` (``"x"`` is the whole state):

* ``error_2 = |x_hat_i[k]_b - x[k]_b|_2``, ``error_inf`` likewise;
* ``relative_error_2 = error_2 / |x[k]_b|_2`` -- the metric for unstable plants, whose
  absolute error in float64 has a floor of about 1e-15 |x|.

A round in which an agent published nothing (crashed, not yet joined) is NaN.
"""

from __future__ import annotations

import numpy as np

from scenarios.build import Experiment

METRICS = ("error_2", "error_inf", "relative_error_2")


class Monitor:
    """Collects per-round errors into dense arrays ``(rounds, agents, blocks)``.

    Estimates are buffered for a chunk of rounds (at most ~64 MB) and the norms computed
    for the whole chunk at once, which keeps the per-round cost of the monitor small.
    """

    CHUNK_BYTES = 64 * 2**20

    def __init__(self, exp: Experiment) -> None:
        self.exp = exp
        K = exp.n_rounds + 1
        self.block_names = list(exp.blocks)
        self._blocks = [exp.blocks[b] for b in self.block_names]
        self._whole = [len(idx) == exp.n for idx in self._blocks]
        shape = (K, exp.N, len(self._blocks))
        self.error_2 = np.full(shape, np.nan)
        self.error_inf = np.full(shape, np.nan)
        self.relative_error_2 = np.full(shape, np.nan)
        self.truth_norm = np.full((K, len(self._blocks)), np.nan)
        self.last_round = -1
        self._chunk = max(1, min(1024, self.CHUNK_BYTES // max(1, exp.N * exp.n * 8)))
        self._est = np.full((self._chunk, exp.N, exp.n), np.nan)
        self._x = np.zeros((self._chunk, exp.n))
        self._rows: list[int] = []

    def record(self, k: int, x: np.ndarray, estimates: np.ndarray, present: np.ndarray | None = None) -> None:
        """Record round ``k``: ``x`` (n,), ``estimates`` (N, n); ``present`` (N,) bool mask
        (absent agents are NaN)."""
        r = len(self._rows)
        self._est[r] = estimates
        if present is not None:
            self._est[r, ~present] = np.nan
        self._x[r] = x
        self._rows.append(k)
        self.last_round = max(self.last_round, k)
        if len(self._rows) == self._chunk:
            self.flush()

    def flush(self) -> None:
        """Compute the norms of the buffered rounds."""
        if not self._rows:
            return
        rows = np.array(self._rows)
        c = len(rows)
        E = self._est[:c] - self._x[:c, None, :]
        for b, idx in enumerate(self._blocks):
            Eb = E if self._whole[b] else E[:, :, idx]
            xb = self._x[:c] if self._whole[b] else self._x[:c, idx]
            e2 = np.sqrt(np.einsum("kij,kij->ki", Eb, Eb))
            with np.errstate(invalid="ignore"):
                einf = np.max(np.abs(Eb), axis=2)
            xn = np.sqrt(np.einsum("kj,kj->k", xb, xb))
            self.error_2[rows, :, b] = e2
            self.error_inf[rows, :, b] = einf
            with np.errstate(divide="ignore", invalid="ignore"):
                rel = e2 / xn[:, None]
            rel[(xn[:, None] == 0) & (e2 == 0)] = 0.0
            self.relative_error_2[rows, :, b] = rel
            self.truth_norm[rows, b] = xn
        self._est[:c] = np.nan
        self._rows.clear()

    def current_worst(self) -> float:
        """Worst infinity-norm error of the last recorded round (for progress bars)."""
        if self._rows:
            r = len(self._rows) - 1
            with np.errstate(invalid="ignore"):
                v = np.abs(self._est[r] - self._x[r])
            return float(np.nanmax(v)) if not np.all(np.isnan(v)) else float("nan")
        k = self.last_round
        return float(np.nanmax(self.error_inf[k])) if k >= 0 else float("nan")

    def metric(self, name: str) -> np.ndarray:
        """``(rounds, agents, blocks)`` array of a metric; ``error_ratio`` is ``error_2``
        divided by the agent's ``error_2`` at round 0 (the decay of the initial error)."""
        self.flush()
        if name == "error_ratio":
            with np.errstate(divide="ignore", invalid="ignore"):
                return self.error_2 / self.error_2[:1]
        return {"error_2": self.error_2, "error_inf": self.error_inf, "relative_error_2": self.relative_error_2}[name]
