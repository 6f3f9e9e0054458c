"""Known input signals ``u(t)`` (deterministic functions of time, known to every observer)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Signal:
    """``u(t) = offset + amplitude * sin(omega t + phase)`` per channel (vectors of length p).

    ``kind = "zero"`` gives zeros, ``"constant"`` the offset, ``"sine"`` the full form.
    """

    kind: str
    p: int
    offset: np.ndarray
    amplitude: np.ndarray
    omega: np.ndarray
    phase: np.ndarray

    @classmethod
    def zero(cls, p: int) -> "Signal":
        z = np.zeros(p)
        return cls("zero", p, z, z, z, z)

    @classmethod
    def sine(cls, p: int, *, amplitude=1.0, omega=1.0, phase=0.0, offset=0.0) -> "Signal":
        f = lambda v: np.broadcast_to(np.asarray(v, dtype=float), (p,)).copy()  # noqa: E731
        return cls("sine", p, f(offset), f(amplitude), f(omega), f(phase))

    @classmethod
    def constant(cls, p: int, value=0.0) -> "Signal":
        z = np.zeros(p)
        return cls("constant", p, np.broadcast_to(np.asarray(value, float), (p,)).copy(), z, z, z)

    def __call__(self, t: float) -> np.ndarray:
        if self.kind == "zero":
            return self.offset.copy()
        if self.kind == "constant":
            return self.offset.copy()
        return self.offset + self.amplitude * np.sin(self.omega * t + self.phase)
