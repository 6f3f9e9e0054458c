"""Sensor attack signals ``a_i(t)`` (Lee, Kim, Shim eq. (1b): ``y_i = C_i x + a_i``).

Each attack is active on ``start <= t < stop`` and adds the same scalar waveform to every
row of the targeted banks:

* ``constant``: ``value``
* ``ramp`` (unbounded): ``slope * (t - start)``
* ``sine``: ``amplitude * sin(omega (t - start) + phase)``
* ``random``: i.i.d. uniform on ``[-scale, scale]`` per round and per targeted row, drawn
  from a generator seeded by ``(seed, attack index)``; evaluated once per round in
  increasing round order (both drivers' plant does exactly that).
* ``trajectory`` (dynamics-consistent, Mao-Tabuada's attack model): the targeted rows
  report the output of the plant started from another initial state ``x0_attack``,
  ``y_i[k] = C_i x_a[k]``. For an LTI plant ``x[k+1] = Ad x[k] + Bd u[k]`` the known
  input cancels in ``x_a - x``, so the corruption is ``a[k] = C_rows Ad^k (x0_attack - x0)``
  (per row, not one scalar for all rows), a function of the round alone. It is built
  from ``C`` (the targeted rows of the output matrix), ``Ad``, ``d0 = x0_attack - x0``
  and ``dt`` (round ``k = t / dt``); the trajectory starts at round 0 even when ``start``
  is later (switching it on mid-run is then a jump that a sanity check can see).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class SensorAttackSignal:
    """One configured sensor attack.

    Attributes
    ----------
    rows : (r,) int array  rows of the stacked output ``y`` it corrupts
    kind, start, stop, value, slope, amplitude, omega, phase, scale : see module docstring
    """

    rows: np.ndarray
    kind: str
    start: float
    stop: float
    value: float = 0.0
    slope: float = 0.0
    amplitude: float = 0.0
    omega: float = 0.0
    phase: float = 0.0
    scale: float = 0.0
    rng: np.random.Generator | None = field(default=None, repr=False)
    #: kind "trajectory": targeted rows of C (r, n), the sampled plant Ad (n, n),
    #: d0 = x0_attack - x0 (n,), and the round step dt
    C: np.ndarray | None = field(default=None, repr=False)
    Ad: np.ndarray | None = field(default=None, repr=False)
    d0: np.ndarray | None = field(default=None, repr=False)
    dt: float = 1.0
    _cache: tuple[int, np.ndarray] | None = field(default=None, init=False, repr=False)

    def active(self, t: float) -> bool:
        return self.start <= t < self.stop

    def value_at(self, t: float) -> np.ndarray:
        """The additive corruption ``(r,)`` at time ``t`` (zeros when inactive)."""
        r = len(self.rows)
        if not self.active(t):
            return np.zeros(r)
        if self.kind == "constant":
            return np.full(r, self.value)
        if self.kind == "ramp":
            return np.full(r, self.slope * (t - self.start))
        if self.kind == "sine":
            return np.full(r, self.amplitude * np.sin(self.omega * (t - self.start) + self.phase))
        if self.kind == "random":
            if self.rng is None:
                raise ValueError("random attack needs a generator")
            return self.rng.uniform(-self.scale, self.scale, size=r)
        if self.kind == "trajectory":
            return self.C @ self._offset(int(round(t / self.dt)))
        raise ValueError(f"unknown sensor attack kind {self.kind!r}")

    def _offset(self, k: int) -> np.ndarray:
        """``Ad^k d0`` (kind "trajectory"), advanced from the last round asked for
        (rounds are asked in increasing order; an earlier round restarts from ``d0``)."""
        if self.C is None or self.Ad is None or self.d0 is None:
            raise ValueError("trajectory attack needs C, Ad and d0")
        if self._cache is None or self._cache[0] > k:
            self._cache = (0, np.array(self.d0, dtype=float))
        j, d = self._cache
        while j < k:
            d = self.Ad @ d
            j += 1
        self._cache = (k, d)
        return d
