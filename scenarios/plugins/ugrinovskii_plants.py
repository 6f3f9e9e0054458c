"""The Ugrinovskii plugin's plants (:mod:`scenarios.plugins.ugrinovskii`): the disturbance and
attack signals, and the ``ugrinovskii_example`` and ``hinf`` plant models (exact ZOH steps)."""


from __future__ import annotations

import math
from typing import TYPE_CHECKING, Protocol

import numpy as np

from estimation.errors import ScenarioError
from estimation.lti import ContinuousLTI, zoh
from estimation.ugrinovskii_example import plant_matrix

from ..common import STREAM_ESTIMATOR, STREAM_PLANT_NOISE, PlantModel, rng_for
from ..helpers import explicit_AB, matrix, plant_params

if TYPE_CHECKING:
    from ..schema import Scenario

from .ugrinovskii_schema import BiasingAttack, Disturbance

Amplitude = float | list[float]


# ============================================================================ signals
def _vector(value: Amplitude, dim: int, where: str, source: str) -> np.ndarray:
    v = np.atleast_1d(np.asarray(value, dtype=float))
    if v.size == 1:
        v = np.full(dim, float(v[0]))
    if v.shape != (dim,):
        raise ScenarioError(f"{where}: expected one number or {dim} numbers, got {v.size}", source=source)
    if not np.all(np.isfinite(v)):
        raise ScenarioError(f"{where}: entries must be finite", source=source)
    return v


class DisturbanceSignal:
    """A :class:`Disturbance` of dimension ``dim`` as a function of the round: ``at(k)``
    is its value held over ``[t_k, t_{k+1})``. White noise is drawn from
    ``rng_for(seed, *stream, k)`` (a pure function of the round)."""

    def __init__(self, spec: Disturbance, dim: int, *, dt: float, seed: int, stream: tuple[int, ...],
                 where: str = "disturbance", source: str = "<scenario>") -> None:
        self.kind, self.dim, self.dt = spec.kind, int(dim), float(dt)
        self.seed, self.stream = int(seed), tuple(int(s) for s in stream)
        self.k0 = int(math.ceil(spec.start / dt - 1e-9))
        self.k1 = int(math.ceil((spec.start + spec.duration) / dt - 1e-9)) if math.isfinite(spec.duration) else None
        self.amplitude = _vector(spec.amplitude, dim, f"{where}.amplitude", source)
        self.scale = math.sqrt(spec.intensity / dt)
        if self.kind == "white" and spec.intensity == 0:
            self.kind = "zero"
        self._zero = np.zeros(self.dim)

    @property
    def zero(self) -> bool:
        return self.kind == "zero" or self.dim == 0

    def at(self, k: int) -> np.ndarray:
        if self.zero or k < self.k0 or (self.k1 is not None and k >= self.k1):
            return self._zero
        if self.kind == "pulse":
            return self.amplitude
        return self.scale * rng_for(self.seed, *self.stream, k).standard_normal(self.dim)


class AttackSignal:
    """The attacker's input ``f(t)`` at one node and target: the sum of the node's
    :class:`BiasingAttack` s (a picklable callable ``t -> (nf,)``; ``t`` is a round time
    ``k dt``, the node holds ``f(t_{k-1})`` over ``[t_{k-1}, t_k)``)."""

    def __init__(self, specs: list[tuple[int, BiasingAttack]], nf: int, *, dt: float, seed: int, source: str) -> None:
        self.dt, self.nf, self.seed = float(dt), int(nf), int(seed)
        self.parts = []
        for idx, a in specs:
            where = f"estimator.biasing[{idx}]"
            k0 = int(math.ceil(a.start / dt - 1e-9))
            k1 = int(math.ceil((a.start + a.duration) / dt - 1e-9)) if math.isfinite(a.duration) else None
            self.parts.append((idx, k0, k1, a.start, _vector(a.amplitude, nf, f"{where}.amplitude", source), a.rise,
                               _vector(a.masking, nf, f"{where}.masking", source), a.masking_decay, a.masking_omega,
                               a.masking_noise))

    def __call__(self, t: float) -> np.ndarray:
        k = int(round(t / self.dt))
        f = np.zeros(self.nf)
        for idx, k0, k1, start, amp, rise, mask, decay, omega, noise in self.parts:
            if k < k0 or (k1 is not None and k >= k1):
                continue
            s = max(k * self.dt - start, 0.0)
            f += amp * (min(1.0, s / rise) if rise > 0 else 1.0)
            if np.any(mask):
                f += mask * math.exp(-s / decay) * math.cos(omega * s)
            if noise > 0:
                f += noise * rng_for(self.seed, STREAM_ESTIMATOR, 2, idx, k).standard_normal(self.nf)
        return f


# ============================================================================ plants
class Signal(Protocol):
    """A disturbance held over each step: its value at round ``k``, shape ``(dim,)``."""

    dim: int

    @property
    def zero(self) -> bool: ...

    def at(self, k: int) -> np.ndarray: ...


class HinfPlant:
    """``x' = A x + B w``, ``y = C x + D v`` (all banks stacked), exact at step ``dt``
    with ``w``, ``v`` held over each step (a :class:`scenarios.common.PlantStepper`)."""

    def __init__(self, A: np.ndarray, B: np.ndarray, C: np.ndarray, d: float, *, dt: float,
                 w: Signal, v: Signal) -> None:
        self.A, self.B, self.C = A, B, C
        self.d = float(d)
        self.D = self.d * np.eye(C.shape[0])
        self.Ad, self.Bd = zoh(A, B, dt)
        self.w, self.v = w, v

    def measure(self, k: int, x: np.ndarray) -> np.ndarray:
        y = self.C @ x
        return y if self.v.zero else y + self.d * self.v.at(k)

    def advance(self, k: int, x: np.ndarray) -> np.ndarray:
        x = self.Ad @ x
        return x if self.w.zero else x + self.Bd @ self.w.at(k)


_NOISE_DEFAULTS = {
    "w_white": 0.0, "w_pulse": 0.0, "w_pulse_start": 0.0, "w_pulse_duration": 1.0,
    "v_white": 0.0, "v_pulse": 0.0, "v_pulse_start": 0.0, "v_pulse_duration": 1.0,
}
_EXAMPLE = {"b": 0.1, "d": 0.01, **_NOISE_DEFAULTS}
_HINF = {"d": 0.01, **_NOISE_DEFAULTS}


def _disturbance(p: dict, name: str, dim: int, sc: "Scenario", source: str) -> Signal:
    """``w`` or ``v`` from the flat plant parameters ``{name}_white``, ``{name}_pulse*``:
    white noise plus a pulse (their sum)."""
    white = Disturbance(kind="white", intensity=p[f"{name}_white"])
    pulse = Disturbance(kind="pulse", amplitude=p[f"{name}_pulse"], start=p[f"{name}_pulse_start"],
                        duration=p[f"{name}_pulse_duration"])
    tag = 0 if name == "w" else 1
    sigs = [DisturbanceSignal(white, dim, dt=sc.run.dt, seed=sc.run.seed, stream=(STREAM_PLANT_NOISE, tag), source=source),
            DisturbanceSignal(pulse, dim, dt=sc.run.dt, seed=sc.run.seed, stream=(STREAM_PLANT_NOISE, tag), source=source)]
    sigs = [s for s in sigs if not s.zero and (s.kind != "pulse" or np.any(s.amplitude))]
    if not sigs:
        return DisturbanceSignal(Disturbance(), dim, dt=sc.run.dt, seed=sc.run.seed, stream=(STREAM_PLANT_NOISE, tag))
    if len(sigs) == 1:
        return sigs[0]
    return _SumSignal(sigs)


class _SumSignal:
    def __init__(self, parts: list[DisturbanceSignal]) -> None:
        self.parts, self.dim, self.zero = parts, parts[0].dim, False

    def at(self, k: int) -> np.ndarray:
        return sum((p.at(k) for p in self.parts), np.zeros(self.dim))


def _plant(sc: "Scenario", source: str, model: str) -> PlantModel:
    pl = sc.plant
    defaults = _EXAMPLE if model == "ugrinovskii_example" else _HINF
    p = plant_params(pl, defaults, source)
    for key in ("w_white", "v_white"):
        if p[key] < 0:
            raise ScenarioError(f"plant.params.{key}: a noise intensity must be >= 0, got {p[key]}", source=source)
    for key in ("w_pulse_duration", "v_pulse_duration"):
        if not (p[key] > 0 and math.isfinite(p[key])):
            raise ScenarioError(f"plant.params.{key}: a pulse needs a finite duration > 0, got {p[key]}", source=source)
    if not p["d"] > 0:
        raise ScenarioError(f"plant.params.d: D_i = d I needs d > 0 (D_i D_i' invertible), got {p['d']}", source=source)
    if pl.time == "discrete":
        raise ScenarioError(f"plant.time: model {model!r} is a continuous-time plant", source=source)
    if pl.input.kind != "zero":
        raise ScenarioError(f"plant.input: model {model!r} has no known input (its B is the disturbance matrix of x' = A x + B w)",
                            source=source)
    if model == "ugrinovskii_example":
        if pl.A is not None or pl.B is not None:
            raise ScenarioError("plant: A and B are given by model 'ugrinovskii_example'; use model = 'hinf' for explicit matrices",
                                source=source)
        if sc.sensors is not None:
            raise ScenarioError("sensors: the sensors are given by model 'ugrinovskii_example' (sensor i measures x_i and x_i+1)",
                                source=source)
        A = plant_matrix()
        n = A.shape[0]
        B = p["b"] * np.eye(n)
        eye = np.eye(n)
        banks = tuple(eye[[i, (i + 1) % n]] for i in range(n))
    else:
        A, B = explicit_AB(pl, source)
        n = A.shape[0]
        if sc.sensors is None:
            raise ScenarioError("sensors: required for model = 'hinf' (one [[sensors]] table per node's C_i)", source=source)
        banks = tuple(matrix(s.C, f"sensors[{k}].C", source, cols=n) for k, s in enumerate(sc.sensors))
    names = tuple(pl.state_names) if pl.state_names else tuple(f"x{i + 1}" for i in range(n))
    if len(names) != n:
        raise ScenarioError(f"plant.state_names: expected {n} names, got {len(names)}", source=source)
    C = np.vstack(banks)
    stepper = HinfPlant(A, B, C, p["d"], dt=sc.run.dt, w=_disturbance(p, "w", B.shape[1], sc, source),
                        v=_disturbance(p, "v", C.shape[0], sc, source))
    lti = ContinuousLTI(A=A, B=np.zeros((n, 0)), banks=banks, state_names=names)
    return PlantModel(lti=lti, discrete=False, stepper=stepper, info={"B": B, "d": p["d"]})


PLANTS = {
    "ugrinovskii_example": (_EXAMPLE, lambda sc, source: _plant(sc, source, "ugrinovskii_example")),
    "hinf": (_HINF, lambda sc, source: _plant(sc, source, "hinf")),
}
