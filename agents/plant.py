"""The plant role: advances the true state and serves the sensing locations.

Round ``k``: ``x[k]`` is the state at ``t_k = k dt``; :meth:`measure` returns the stacked
``y[k] = C x[k] + a(t_k)`` with the sensor attacks applied; :meth:`advance` moves to
``x[k+1] = Ad x[k] + Bd u(t_k)`` (exact zero-order hold, :func:`estimation.lti.zoh`, or
the discrete-time plant itself). A nonlinear or noisy plant brings its own stepper
(:class:`scenarios.common.PlantStepper`), which replaces the output map and the step.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # the plant process is handed a slice of the experiment (agents.net.slices)
    from .rounds import PlantTeam


class PlantRole:
    def __init__(self, exp: PlantTeam) -> None:
        self.exp = exp
        self.x = exp.x0.copy()
        self._C = exp.C
        self._Ad, self._Bd = exp.Ad, exp.Bd
        self._input = exp.input
        self._attacks = exp.sensor_attacks
        self._stepper = exp.stepper
        self.k = 0

    @property
    def truth(self) -> np.ndarray:
        return self.x.copy()

    def measure(self, k: int) -> np.ndarray:
        t = k * self.exp.dt
        y = self._C @ self.x if self._stepper is None else np.array(self._stepper.measure(k, self.x), dtype=float)
        for a in self._attacks:
            if a.active(t):
                y[a.rows] += a.value_at(t)
        return y

    def advance(self, k: int) -> None:
        if self._stepper is not None:
            self.x = np.asarray(self._stepper.advance(k, self.x), dtype=float)
        else:
            self.x = self._Ad @ self.x + self._Bd @ self._input(k * self.exp.dt)
        self.k = k + 1
