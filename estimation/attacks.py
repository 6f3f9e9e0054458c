"""Sensor attack signals ``a_i(t)`` (Lee, Kim, Shim eq. (1b): ``y_i = C_i x + a_i``).

Each attack is active on ``start <= t < stop`` and adds the same scalar waveform to every
row of the targeted banks:

* ``constant``: ``value``
* ``ramp`` (unbounded): ``slope * (t - start)``
* ``sine``: ``amplitude * sin(omega (t - start) + phase)``
* ``random``: i.i.d. uniform on ``[-scale, scale]`` per round and per targeted row, drawn
  from a generator seeded by ``(seed, attack index)``; evaluated once per round in
  increasing round order (both drivers' plant does exactly that).
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
        raise ValueError(f"unknown sensor attack kind {self.kind!r}")
