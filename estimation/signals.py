"""Known input signals ``u(t)`` (deterministic functions of time, known to every observer)."""

from __future__ import annotations

from dataclasses import dataclass, field

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
    _last: list = field(default_factory=lambda: [None, None], repr=False, compare=False)

    @classmethod
    def zero(cls, p: int) -> "Signal":
        z = np.zeros(p)
        return cls("zero", p, z, z, z, z)

    @classmethod
    def sine(cls, p: int, *, amplitude=1.0, omega=1.0, phase=0.0, offset=0.0) -> "Signal":
        f = lambda v: np.broadcast_to(np.asarray(v, dtype=float), (p,)).copy()
        return cls("sine", p, f(offset), f(amplitude), f(omega), f(phase))

    @classmethod
    def constant(cls, p: int, value=0.0) -> "Signal":
        z = np.zeros(p)
        return cls("constant", p, np.broadcast_to(np.asarray(value, float), (p,)).copy(), z, z, z)

    def __call__(self, t: float) -> np.ndarray:
        """``u(t)``, shape ``(p,)``, read-only (the last value is cached: every agent of a
        round asks for the same ``t``)."""
        last = self._last
        if last[0] == t:
            return last[1]
        if self.kind in ("zero", "constant"):
            u = self.offset.copy()
        else:
            u = self.offset + self.amplitude * np.sin(self.omega * t + self.phase)
        u.flags.writeable = False
        last[0], last[1] = t, u
        return u
