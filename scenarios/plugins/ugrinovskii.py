"""Plugin: Ugrinovskii, "Distributed H-infinity estimation resilient to biasing attacks".

Controlled distributed H-infinity observers (8) with attack detectors / compensators
(17)-(19) (``controlled = true``) or the same observers without the controllers
(``controlled = false``, the baseline of Fig. 1(a), same ``L``, ``K`` gains), on the
named plants

* ``ugrinovskii_example``: Section IV (6-state ``A``, ``B = b I``, sensor ``i`` measuring
  coordinates ``i`` and ``i + 1``, ``D_i = d I``);
* ``hinf``: explicit ``A``, ``B`` (the disturbance matrix of ``x' = A x + B w``) and
  ``[[sensors]]`` ``C_i``, with ``D_i = d I``.

Both plants are integrated exactly at the round step with the disturbances held over each
step (zero-order hold): ``x[k+1] = expm(A dt) x[k] + Bd w(t_k)``, ``y_i[k] = C_i x[k] +
D_i v_i(t_k)``. Disturbances (``w``, ``v_i``; the neighbours' channel noise ``v_ij``,
``v_c,ij``) are :class:`DisturbanceSignal` s: zero, white noise of a given intensity
(held samples of variance ``intensity / dt``: band-limited white noise whose spectral
density is ``intensity``), or rectangular L2 pulses, each seeded from
``(run seed, stream, index, round)`` so both drivers draw the same numbers in any order.

The offline design (the LMIs (34), (40), (52), :func:`estimation.hinf_lmi.design`) is done
once per run and cached (``exp.design``; in memory per process; in the file
``estimator.design_cache`` when given, a ``.npz`` or a run's ``design.json``). See
``docs/algorithms/ugrinovskii.md``.
"""

from __future__ import annotations

import hashlib
import json
import math
import re
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
from pydantic import Field, model_validator

from estimation import graphs
from estimation.base import Diagnostics, Flags
from estimation.errors import DesignError, NumericalError, ScenarioError
from estimation.hinf_lmi import ResilientProblem, closed_form_design, node_riccati_data
from estimation.hinf_lmi import design as lmi_design
from estimation.hinf_riccati import RiccatiFlow
from estimation.lti import ContinuousLTI, zoh
from estimation.ugrinovskii import UgrinovskiiBaseline, UgrinovskiiNode, first_order_attack_model
from estimation.ugrinovskii_example import PAPER_GAMMA2, PAPER_GAMMA2_BAR, example_problem, plant_matrix

from ..common import STREAM_AGENT_X0, STREAM_ESTIMATOR, STREAM_PLANT_NOISE, Condition, PlantModel, checked_design, rng_for
from ..helpers import explicit_AB, init_vector, matrix
from ..types import Init, Matrix, Strict, ZeroInit

if TYPE_CHECKING:
    from ..build import Experiment
    from ..schema import Scenario

Amplitude = float | list[float]


# ============================================================================ schema
class Disturbance(Strict):
    """A disturbance signal: ``zero``; ``white`` (intensity = spectral density of each
    component; held samples of variance ``intensity / dt``); ``pulse`` (``amplitude`` on
    ``[start, start + duration)``, an L2 signal). ``white`` is windowed the same way."""

    kind: Literal["zero", "white", "pulse"] = "zero"
    intensity: float = Field(default=0.0, ge=0)
    amplitude: Amplitude = 0.0
    start: float = Field(default=0.0, ge=0)
    duration: float = Field(default=math.inf, gt=0)

    @model_validator(mode="after")
    def _finite_pulse(self) -> "Disturbance":
        if self.kind == "pulse" and not math.isfinite(self.duration):
            raise ValueError("a pulse needs a finite duration (an L2 signal)")
        return self


class BiasingAttack(Strict):
    """A biasing attack of the admissible class (Definition 1) on node ``node``:
    ``f = f_1 + f_2`` on ``[start, start + duration)``, 0 elsewhere, with the slow biasing
    part ``f_1 = amplitude * min(1, (t - start) / rise)`` (a step when ``rise = 0``) and the
    L2 masking part ``f_2 = masking exp(-(t - start) / masking_decay) cos(masking_omega
    (t - start))`` plus seeded white noise of standard deviation ``masking_noise`` (held
    over each step). ``target = "observer"`` injects ``F_i f`` into (8); ``"detector"``
    injects ``F_c,i f`` into (17) (needs ``detector_attack_matrix = "F"``)."""

    node: int = Field(ge=1, description="1-based agent id")
    target: Literal["observer", "detector"] = "observer"
    start: float = Field(default=0.0, ge=0)
    duration: float = Field(default=math.inf, gt=0)
    amplitude: Amplitude = 0.0
    rise: float = Field(default=0.0, ge=0)
    masking: Amplitude = 0.0
    masking_decay: float = Field(default=1.0, gt=0)
    masking_omega: float = 0.0
    masking_noise: float = Field(default=0.0, ge=0)


class UgrinovskiiEstimator(Strict):
    """Ugrinovskii: controlled distributed H-infinity observers resilient to biasing attacks."""

    algorithm: Literal["ugrinovskii"]
    #: true: observers (8) with the controllers (17)-(19); false: the baseline (8) with u = 0
    controlled: bool = True
    #: how the offline design is made: the LMIs, or footnote 3's closed form (needs gamma2, gamma2_bar)
    method: Literal["lmi", "closed_form"] = "lmi"
    #: relative back-off from the LMI optimum of gamma^2 and gamma_bar^2
    backoff: float = Field(default=0.05, ge=0)
    gamma2: float | None = Field(default=None, gt=0)
    gamma2_bar: float | None = Field(default=None, gt=0)
    #: channel noise in the observer LMI's Ubar: "H" (38) or "H_hat" (reproduces the paper)
    observer_channel: Literal["H", "H_hat"] = "H_hat"
    solver: str = "CLARABEL"
    #: G_i(s) = attack_gain / (s + attack_pole) (Lemma 1), realisation (13) of -G_i(s)/s
    attack_gain: float = Field(default=410.0, gt=0)
    attack_pole: float = Field(default=40.0, gt=0)
    #: F_i, (n, nf) (default [1 ... 1]'); the detector attack matrix F_c,i = 0 or [F_i; 0]
    F: Matrix | None = None
    detector_attack_matrix: Literal["zero", "F"] = "zero"
    #: what neighbours share, W_ij (p x n, default I); channel noise matrices H_ij, H_c,ij
    #: (p x r, default (0.1 / sqrt 2) [1 ... 1]'; H_c defaults to H); Z_ij = Z I, Zbar_ij = Zbar I
    W: Matrix | None = None
    H: Matrix | None = None
    Hc: Matrix | None = None
    Z: float = Field(default=0.01, gt=0)
    Zbar: float = Field(default=0.01, gt=0)
    #: the noise v_ij on c_ij (3) and v_c,ij on eta_ij (18), added by the receiver
    channel_noise: Disturbance = Field(default_factory=Disturbance)
    controller_noise: Disturbance = Field(default_factory=Disturbance)
    biasing: list[BiasingAttack] = Field(default_factory=list)
    #: a node flags an attack when max |u_i| has stayed above threshold for hold seconds
    threshold: float = Field(default=1.0, gt=0)
    hold: float = Field(default=0.05, ge=0)
    #: flags are raised from this time on only (the initial estimation errors move every u_i)
    flag_from: float = Field(default=0.0, ge=0)
    #: initial estimates xi_i (e_hat, eps_hat start at 0)
    x0: Init = Field(default_factory=ZeroInit)
    #: the node re-discretises when a Riccati solution moved by more than this (relative)
    gain_rtol: float = Field(default=1e-3, ge=0)
    #: a .npz (read if it matches, else written) or a run's design.json (read) with the design
    design_cache: str | None = None

    @model_validator(mode="after")
    def _closed_form(self) -> "UgrinovskiiEstimator":
        if self.method == "closed_form" and (self.gamma2 is None or self.gamma2_bar is None):
            raise ValueError("method 'closed_form' needs gamma2 and gamma2_bar")
        if self.method == "lmi" and (self.gamma2 is not None or self.gamma2_bar is not None):
            raise ValueError("gamma2 and gamma2_bar are results of method 'lmi'; give them for method 'closed_form' only")
        return self


ESTIMATOR = UgrinovskiiEstimator


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
class HinfPlant:
    """``x' = A x + B w``, ``y = C x + D v`` (all banks stacked), exact at step ``dt``
    with ``w``, ``v`` held over each step (a :class:`scenarios.common.PlantStepper`)."""

    def __init__(self, A: np.ndarray, B: np.ndarray, C: np.ndarray, d: float, *, dt: float,
                 w: DisturbanceSignal, v: DisturbanceSignal) -> None:
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


def _disturbance(p: dict, name: str, dim: int, sc: "Scenario", source: str) -> DisturbanceSignal:
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
    unknown = set(pl.params) - set(defaults)
    if unknown:
        raise ScenarioError(f"plant.params: unknown parameter(s) {sorted(unknown)}; expected some of {sorted(defaults)}", source=source)
    p = {**defaults, **pl.params}
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


# ============================================================================ design
@dataclass
class UgrinovskiiDesign:
    """``exp.design``: the problem (plain matrices), the LMI (or closed-form) result
    (a dict of arrays, ``numpy.savez``-able) and where the result came from."""

    problem: ResilientProblem
    result: dict[str, np.ndarray]
    source: str  # "solved", "memory" or "file <path>"
    key: str


#: results solved in this process, by problem and options (a run builds once; tests and
#: ``rse agent``, which validates then builds, do not solve twice)
_MEMO: "OrderedDict[str, dict[str, np.ndarray]]" = OrderedDict()
_MEMO_SIZE = 8


def _matrix_opt(rows: Matrix | None, default: np.ndarray, where: str, source: str, *, nrows: int | None = None,
                cols: int | None = None) -> np.ndarray:
    if rows is None:
        return default
    return matrix(rows, where, source, nrows=nrows, cols=cols)


def _plant_data(exp: "Experiment") -> HinfPlant:
    st = exp.stepper
    if not isinstance(st, HinfPlant):
        raise ScenarioError(f"estimator.algorithm: 'ugrinovskii' needs plant.model 'ugrinovskii_example' or 'hinf' (they carry "
                            f"the disturbance matrices B and D_i), got {exp.scenario.plant.model!r}", source=exp.source)
    return st


def problem_of(exp: "Experiment") -> ResilientProblem:
    """The :class:`~estimation.hinf_lmi.ResilientProblem` of a scenario (node ``i`` = agent
    index ``i``; ``V_i`` = its in-neighbours in ``network.graph``)."""
    est, source = exp.scenario.estimator, exp.source
    st = _plant_data(exp)
    if not exp.static:
        raise ScenarioError("estimator.algorithm: 'ugrinovskii' needs static agents ([[agents]] with sensors)", source=source)
    n, N = exp.n, exp.N
    C = tuple(exp.plant.C[rows] for rows in exp.agent_rows)
    D = tuple(st.D[np.ix_(rows, rows)] for rows in exp.agent_rows)
    for i, c in enumerate(C):
        if c.shape[0] == 0:
            raise ScenarioError(f"agents: agent {exp.agent_ids[i]} reads no sensor", source=source)
    F = _matrix_opt(est.F, np.ones((n, 1)), "estimator.F", source, nrows=n)
    nf = F.shape[1]
    Om, Ga, Up = first_order_attack_model(gain=est.attack_gain, pole=est.attack_pole)
    if nf > 1:  # G_i(s) = g/(s+p) I: one realisation per attack component
        Om, Ga, Up = (np.kron(np.eye(nf), M) for M in (Om, Ga, Up))
    ne = Om.shape[0]
    Fc = np.vstack([F, np.zeros((ne, nf))]) if est.detector_attack_matrix == "F" else np.zeros((n + ne, nf))
    W = _matrix_opt(est.W, np.eye(n), "estimator.W", source, cols=n)
    pW = W.shape[0]
    H = _matrix_opt(est.H, (0.1 / math.sqrt(2.0)) * np.ones((pW, 1)), "estimator.H", source, nrows=pW)
    Hc = _matrix_opt(est.Hc, H, "estimator.Hc", source, nrows=pW)
    neighbours = tuple(tuple(exp.in_neighbours(i)) for i in range(N))
    edges = [(i, j) for i in range(N) for j in neighbours[i]]
    Adj = (np.asarray(exp.Adj) != 0).astype(float)
    Lap = np.diag(Adj.sum(axis=1)) - Adj
    LapT = np.diag(Adj.T.sum(axis=1)) - Adj.T
    try:
        return ResilientProblem(
            A=exp.plant.A, B=st.B, C=C, D=D, neighbours=neighbours,
            W={e: W for e in edges}, H={e: H for e in edges}, Hc={e: Hc for e in edges},
            Z={e: est.Z * np.eye(pW) for e in edges}, Zbar={e: est.Zbar * np.eye(pW) for e in edges},
            F=(F,) * N, Fc=(Fc,) * N, Omega=(Om,) * N, Gamma=(Ga,) * N, Upsilon=(Up,) * N,
            P=np.kron(Lap + LapT, np.eye(n)),
        )
    except DesignError as exc:
        raise ScenarioError(f"estimator: {exc}", source=source) from None


def _key(problem: ResilientProblem, est: UgrinovskiiEstimator) -> str:
    """A digest of everything the design depends on."""
    h = hashlib.sha256()

    def add(a: Any) -> None:
        a = np.ascontiguousarray(np.asarray(a, dtype=float))
        h.update(str(a.shape).encode())
        h.update(a.tobytes())

    for name in ("A", "B", "P"):
        add(getattr(problem, name))
    for name in ("C", "D", "F", "Fc", "Omega", "Gamma", "Upsilon"):
        for a in getattr(problem, name):
            add(a)
    h.update(repr(problem.neighbours).encode())
    for name in ("W", "H", "Hc", "Z", "Zbar"):
        for e in problem.edges:
            add(getattr(problem, name)[e])
    opts = (est.method, est.backoff, est.observer_channel, est.solver, est.gamma2, est.gamma2_bar)
    h.update(repr(opts).encode())
    return h.hexdigest()[:32]


def _load_cache(path: Path) -> dict[str, np.ndarray]:
    if path.suffix == ".json":
        data = json.loads(path.read_text())
        res = data.get("lmi", data)
        return {k: np.asarray(v) for k, v in res.items()}
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def _solve(problem: ResilientProblem, est: UgrinovskiiEstimator) -> dict[str, np.ndarray]:
    if est.method == "closed_form":
        return closed_form_design(problem, gamma2=est.gamma2, gamma2_bar=est.gamma2_bar,
                                  observer_channel=est.observer_channel)
    return lmi_design(problem, backoff=est.backoff, observer_channel=est.observer_channel, solver=est.solver)


def design(exp: "Experiment", *, check: bool = True) -> UgrinovskiiDesign | None:
    """The problem, and the LMI design done once: from this process's memo, from
    ``estimator.design_cache`` (checked against the problem by
    :func:`estimation.hinf_lmi.check_design`) or solved (then written to the cache file)."""
    est, source = exp.scenario.estimator, exp.source
    if exp.discrete:
        raise ScenarioError("estimator.algorithm: 'ugrinovskii' is a continuous-time observer; the plant is discrete-time",
                            source=source)
    problem = problem_of(exp)
    for (i, _), specs in _attack_specs(exp).items():  # validate the attacks and noise before the (slow) design
        AttackSignal(specs, problem.F[i].shape[1], dt=exp.dt, seed=exp.seed, source=source)
    for name, mats in (("channel_noise", problem.H), ("controller_noise", problem.Hc)):
        for _e, M in list(mats.items())[:1]:
            DisturbanceSignal(getattr(est, name), M.shape[1], dt=exp.dt, seed=exp.seed, stream=(), where=f"estimator.{name}",
                              source=source)
    key = _key(problem, est)
    path = Path(est.design_cache) if est.design_cache else None
    origin = "memory"
    try:
        res = _MEMO.get(key)
        if res is not None:
            _MEMO.move_to_end(key)
            res = {k: v.copy() for k, v in res.items()}
        elif path is not None and path.exists():
            try:
                cached = _load_cache(path)
            except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
                raise ScenarioError(f"estimator.design_cache: cannot read {path}: {exc}", source=source) from None
            if str(cached.get("cache_key", "")) == key:
                res = lmi_design(problem, cached=cached)  # checked against the problem (check_design)
                origin = f"file {path}"
            elif path.suffix == ".json":
                raise ScenarioError(f"estimator.design_cache: {path} holds the design of another problem or other "
                                    "design options", source=source)
        if res is None:
            res = _solve(problem, est)
            res["cache_key"] = np.array(key)
            origin = "solved"
    except DesignError as exc:
        if not check:
            return None
        raise ScenarioError(f"estimator: {_agent_names(str(exc), exp.agent_ids)}", source=source) from None
    if path is not None and path.suffix != ".json" and not origin.startswith("file"):
        path.parent.mkdir(parents=True, exist_ok=True)
        with path.open("wb") as fh:
            np.savez(fh, **res)
    _MEMO[key] = {k: v.copy() for k, v in res.items()}
    while len(_MEMO) > _MEMO_SIZE:
        _MEMO.popitem(last=False)
    return UgrinovskiiDesign(problem, res, origin, key)


def _agent_names(msg: str, ids: list[int]) -> str:
    """The core numbers nodes 0..N-1; scenario files use agent ids."""
    return re.sub(r"\bnode (\d+)", lambda m: f"agent {ids[int(m.group(1))]}" if int(m.group(1)) < len(ids) else m.group(0), msg)


def _attack_specs(exp: "Experiment") -> dict[tuple[int, str], list[tuple[int, BiasingAttack]]]:
    est, source = exp.scenario.estimator, exp.source
    out: dict[tuple[int, str], list[tuple[int, BiasingAttack]]] = {}
    for k, a in enumerate(est.biasing):
        if a.node not in exp.agent_ids:
            raise ScenarioError(f"estimator.biasing[{k}].node: no agent {a.node}; agents are "
                                f"{', '.join(map(str, exp.agent_ids))}", source=source)
        if a.target == "detector" and est.detector_attack_matrix == "zero" and est.controlled:
            raise ScenarioError(f"estimator.biasing[{k}].target: an attack on the detector enters through F_c,i, which is 0 "
                                "with detector_attack_matrix = 'zero'; set detector_attack_matrix = 'F'", source=source)
        out.setdefault((exp.agent_ids.index(a.node), a.target), []).append((k, a))
    return out


# ============================================================================ estimators
class _Runtime(Diagnostics, Flags):
    """What the runtime adds to the core nodes: receiver-side channel noise ``H_ij v_ij``
    on ``c_ij`` and ``H_c,ij v_c,ij`` on ``eta_ij`` (for neighbours heard from), the
    attack flag and the diagnostics (``u_i``, and the attacker's ``f``, ``f_c`` for plots)."""

    def _setup(self, *, noise_c: list | None, noise_eta: list | None, threshold: float, hold: float,
               flag_from: float, f_obs: AttackSignal | None, f_det: AttackSignal | None) -> None:
        self._noise_c, self._noise_eta = noise_c, noise_eta
        self.threshold, self.hold, self.flag_from = float(threshold), float(hold), float(flag_from)
        self._f_obs, self._f_det = f_obs, f_det
        self._above_since: float | None = None
        self._flagged = False

    def _inputs(self, measurement, inbox):
        v = super()._inputs(measurement, inbox)
        if self._k is None or (self._noise_c is None and self._noise_eta is None):
            return v
        k = self._k  # the step starts at t_{k}: the noise is held over it
        off = self._p
        pj = self._pj
        eta0 = self._p + sum(pj)
        for a, j in enumerate(self._nb):
            if j not in self._last:
                off += pj[a]
                continue
            if self._noise_c is not None:
                H, sig = self._noise_c[a]
                v[off:off + pj[a]] += H @ sig.at(k)
            if self._noise_eta is not None and self._controlled:
                Hc, sig = self._noise_eta[a]
                e0 = eta0 + sum(pj[:a])
                v[e0:e0 + pj[a]] += Hc @ sig.at(k)
            off += pj[a]
        return v

    def _after_step(self) -> None:
        t = self.t
        above = t >= self.flag_from - 1e-9 * max(1.0, self.flag_from) and \
            bool(np.max(np.abs(self.attack_indicator), initial=0.0) > self.threshold)
        if above:
            if self._above_since is None:
                self._above_since = t
            self._flagged = t - self._above_since >= self.hold - 1e-9 * max(1.0, self.hold)
        else:
            self._above_since, self._flagged = None, False

    @property
    def flagged(self) -> bool:
        """``max |u_i|`` has stayed above ``threshold`` for at least ``hold`` seconds (counted
        from ``flag_from`` at the earliest); not latched: it drops when ``|u_i|`` does."""
        return self._flagged

    def diagnostics(self) -> dict[str, float]:
        """``u`` (the attack indicator (19)), ``f`` and ``f_c`` (the attacker's inputs on the
        observer and the detector at this time; 0 when not attacked). Components are numbered
        (``u1``, ``u2``, ...) when ``n_f > 1``."""
        u = self.attack_indicator
        t = self.t
        f = self._f_obs(t) if self._f_obs is not None else np.zeros(self._nf)
        fc = self._f_det(t) if self._f_det is not None else np.zeros(self._nf)
        if self._nf == 1:
            return {"u": float(u[0]), "f": float(f[0]), "f_c": float(fc[0])}
        out = {}
        for name, vec in (("u", u), ("f", f), ("f_c", fc)):
            out.update({f"{name}{c + 1}": float(x) for c, x in enumerate(vec)})
        return out


class ControlledObserver(_Runtime, UgrinovskiiNode):
    """:class:`estimation.ugrinovskii.UgrinovskiiNode` in the runtime (payload ``[x_hat; e_hat]``)."""


class BaselineObserver(_Runtime, UgrinovskiiBaseline):
    """:class:`estimation.ugrinovskii.UgrinovskiiBaseline` in the runtime (payload ``x_hat``; ``u = 0``)."""


def make_estimator(exp: "Experiment", i: int):
    est = exp.scenario.estimator
    des: UgrinovskiiDesign = exp.design
    pb = des.problem
    nf = pb.F[i].shape[1]
    specs = _attack_specs(exp)
    sig = {t: (AttackSignal(specs[(i, t)], nf, dt=exp.dt, seed=exp.seed, source=exp.source) if (i, t) in specs else None)
           for t in ("observer", "detector")}
    if not est.controlled:
        sig["detector"] = None  # the baseline has no detector to attack
    x0 = init_vector(est.x0, exp.n, rng_for(exp.seed, STREAM_AGENT_X0, i), where="estimator.x0")

    def noise(spec: Disturbance, which: int, mats: dict) -> list | None:
        if spec.kind == "zero" or (spec.kind == "white" and spec.intensity == 0):
            return None
        out = []
        for j in pb.neighbours[i]:
            H = mats[(i, j)]
            out.append((H, DisturbanceSignal(spec, H.shape[1], dt=exp.dt, seed=exp.seed,
                                             stream=(STREAM_ESTIMATOR, 1, i, j, which), where="estimator.channel_noise",
                                             source=exp.source)))
        return out

    cls = ControlledObserver if est.controlled else BaselineObserver
    node = cls(pb, des.result, node=i, dt=exp.dt, xi0=x0, observer_attack=sig["observer"],
               detector_attack=sig["detector"], gain_rtol=est.gain_rtol)
    node._setup(noise_c=noise(est.channel_noise, 0, pb.H), noise_eta=noise(est.controller_noise, 1, pb.Hc),
                threshold=est.threshold, hold=est.hold, flag_from=est.flag_from, f_obs=sig["observer"],
                f_det=sig["detector"])
    return node


# ============================================================================ rse check
def graph_conditions(exp: "Experiment") -> list[Condition]:
    """Directed graphs are first-class: the network must be connected (weakly; footnote 1)."""
    Adj = exp.Adj
    comps = graphs.components(Adj)
    undirected = graphs.is_undirected(Adj)
    strong = graphs.is_strongly_connected(Adj)
    kind = "undirected" if undirected else ("directed, strongly connected" if strong else "directed")
    out = [Condition("network connected (weakly; Section II-A, footnote 1)", len(comps) == 1,
                     f"{kind}, {len(comps)} component(s)")]
    lonely = [exp.agent_ids[i] for i in range(exp.N) if not exp.in_neighbours(i)]
    out.append(Condition("in-neighbours V_i", None,
                         "; ".join(f"{exp.agent_ids[i]} <- {','.join(str(exp.agent_ids[j]) for j in exp.in_neighbours(i)) or '-'}"
                                   for i in range(exp.N)) + (f" (no in-neighbour: {lonely})" if lonely else "")))
    return out


def _is_paper_example(exp: "Experiment", pb: ResilientProblem, *, detector: bool) -> bool:
    """The problem is Section IV's (``detector``: for the detector LMIs, which depend on
    ``F_c,i``: the paper's ``F_c,i = 0``; else up to ``F_c,i``, which the observer LMIs do
    not involve)."""
    est = exp.scenario.estimator
    if detector and est.detector_attack_matrix != "zero":
        return False
    ref = example_problem(detector_attack=est.detector_attack_matrix == "F")
    if (pb.n, pb.N) != (ref.n, ref.N) or pb.neighbours != ref.neighbours or est.observer_channel != "H_hat":
        return False
    same = lambda a, b: a.shape == b.shape and np.allclose(a, b, rtol=0, atol=1e-12)
    if not all(same(getattr(pb, m), getattr(ref, m)) for m in ("A", "B", "P")):
        return False
    for m in ("C", "D", "F", "Fc", "Omega", "Gamma", "Upsilon"):
        if not all(same(a, b) for a, b in zip(getattr(pb, m), getattr(ref, m))):
            return False
    return all(same(getattr(pb, m)[e], getattr(ref, m)[e]) for m in ("W", "H", "Hc", "Z", "Zbar") for e in pb.edges)


def riccati_flows(exp: "Experiment", des: UgrinovskiiDesign) -> list[tuple[str, RiccatiFlow]]:
    """Every node's Riccati equations (35) (detector; controlled only) and (41) (observer),
    started from the design (``Y(0) = gamma^2 Q^-1``), at the round step."""
    pb, d = des.problem, des.result
    g, gb = float(d["gamma2"]), float(d["gamma2_bar"])
    flows = []
    for i in range(pb.N):
        nb = pb.neighbours[i]
        aid = exp.agent_ids[i]
        if exp.scenario.estimator.controlled:
            A_, B_, S = node_riccati_data(pb, "det", {(i, j): d[f"U_{i}_{j}"] for j in nb}, i)
            flows.append((f"detector (35) of node {aid}",
                          RiccatiFlow(A=A_, B=B_, S=S, R=d[f"R_{i}"], gamma2=g, Y0=g * np.linalg.inv(d[f"Q_{i}"]),
                                      dt=exp.dt, name=f"detector Riccati (35) of node {aid}")))
        A_, B_, S = node_riccati_data(pb, "obs", {(i, j): d[f"Ubar_{i}_{j}"] for j in nb}, i)
        flows.append((f"observer (41) of node {aid}",
                      RiccatiFlow(A=A_, B=B_, S=S, R=d[f"Rbar_{i}"], gamma2=gb, Y0=gb * np.linalg.inv(d[f"Qbar_{i}"]),
                                  dt=exp.dt, name=f"observer Riccati (41) of node {aid}")))
    return flows


def riccati_report(exp: "Experiment", des: UgrinovskiiDesign) -> dict[str, Any]:
    """Integrate every node's Riccati equations over the horizon (offline: they need no
    communication) and report the smallest eigenvalue and the largest one of each kind.

    Returns ``{"ok": bool, "error": str | None, "horizon": T, "det": [min, max], "obs": [min, max],
    "start": {kind: largest eigenvalue at t = 0}, "trace_ratio": largest trace(Y) / bound}``
    (eigenvalues over all nodes and the horizon; ``kind`` in ``det`` (35), ``obs`` (41)).
    """
    T = exp.n_rounds * exp.dt
    out: dict[str, Any] = {"ok": True, "error": None, "horizon": T, "det": [np.inf, 0.0], "obs": [np.inf, 0.0],
                           "start": {"det": 0.0, "obs": 0.0}, "trace_ratio": 0.0}
    try:
        flows = riccati_flows(exp, des)
        for name, fl in flows:
            kind = "det" if name.startswith("detector") else "obs"
            lam = np.linalg.eigvalsh(fl.Y)
            out["start"][kind] = max(out["start"][kind], float(lam[-1]))
            lo, hi = out[kind]
            lo, hi = min(lo, lam[0]), max(hi, lam[-1])
            tr = float(np.trace(fl.Y))
            for _ in range(exp.n_rounds):
                Y = fl.step()  # raises NumericalError when Y stops being positive definite or bounded
                lam = np.linalg.eigvalsh(Y)
                lo, hi, tr = min(lo, lam[0]), max(hi, lam[-1]), max(tr, float(np.trace(Y)))
            out[kind] = [float(lo), float(hi)]
            out["trace_ratio"] = max(out["trace_ratio"], tr / fl.bound)
    except (NumericalError, DesignError) as exc:
        out["ok"], out["error"] = False, str(exc)
    return out


def conditions(exp: "Experiment") -> list[Condition]:
    """gamma^2, gamma_bar^2 (with the paper's values for Section IV), the back-off, and
    the Riccati solutions over the horizon (positive definite and bounded)."""
    est = exp.scenario.estimator
    des, out = checked_design(exp, design, "LMIs (34), (40), (52) feasible" if est.method == "lmi"
                              else "closed-form design (footnote 3)")
    if des is None:
        return out
    d = des.result
    g, gb = float(d["gamma2"]), float(d["gamma2_bar"])
    if est.method == "lmi":
        how = {"solved": f"solved ({est.solver})", "memory": "solved earlier in this process"}.get(des.source, f"read from the {des.source}")
        out.append(Condition("LMIs (34), (40), (52) feasible", True, f"design {how}"))
        g0, gb0 = float(d["gamma2_opt"]), float(d["gamma2_bar_opt"])
        for name, val, ref, det in (("gamma^2 (detectors, Theorem 1)", g0, PAPER_GAMMA2, True),
                                    ("gamma_bar^2 (observers, Theorem 2)", gb0, PAPER_GAMMA2_BAR, False)):
            if _is_paper_example(exp, des.problem, detector=det):
                rel = val / ref - 1.0
                out.append(Condition(f"{name} within 1% of the paper's", abs(rel) <= 0.01,
                                     f"{val:.5g} (paper {ref:.5g}, relative difference {rel:+.3%})"))
            else:
                note = (" (the paper's example has F_c,i = 0)" if det and _is_paper_example(exp, des.problem, detector=False)
                        else "")
                out.append(Condition(f"{name}: minimum", None, f"{val:.5g}{note}"))
        out.append(Condition("back-off from the LMI optimum", None,
                             f"{float(d['backoff']):.3g}, i.e. {float(d['backoff']):.1%} above the minima: gamma^2 = {g:.5g}, "
                             f"gamma_bar^2 = {gb:.5g} used online"))
    else:
        out.append(Condition("closed-form design (footnote 3)", True, f"gamma^2 = {g:.5g}, gamma_bar^2 = {gb:.5g}"))
    rep = riccati_report(exp, des)
    T = rep["horizon"]
    if rep["ok"]:
        kinds = (("det", "detector Riccati solutions (35)"),) if est.controlled else ()
        for kind, label in kinds + (("obs", "observer Riccati solutions (41)"),):
            lo, hi = rep[kind]
            out.append(Condition(f"{label} positive definite and bounded on [0, {T:g}]", bool(lo > 0 and np.isfinite(hi)),
                                 f"every node: smallest eigenvalue {lo:.3g}, largest {hi:.3g} "
                                 f"(largest at t = 0: {rep['start'][kind]:.3g})"))
        out.append(Condition("Riccati boundedness margin", None,
                             f"largest trace(Y) / bound = {rep['trace_ratio']:.3g} (bound: 1e3 x max(trace Y(0), trace Y_s) "
                             "per equation; Y_s the stationary solution)"))
    else:
        out.append(Condition(f"Riccati solutions positive definite and bounded on [0, {T:g}]", False, rep["error"]))
    out.append(Condition("G_i(s) = gain / (s + pole), (s + G)^-1 G stable (Lemma 1)", True,
                         f"gain {est.attack_gain:g}, pole {est.attack_pole:g}"))
    out.append(Condition("attack flag", None, f"max |u_i| > {est.threshold:g} for {est.hold:g} s"
                         + (f", from t = {est.flag_from:g}" if est.flag_from > 0 else "")))
    return out


def design_json(exp: "Experiment") -> dict:
    des: UgrinovskiiDesign | None = exp.design
    if des is None:
        return {}
    d = des.result
    return {
        "controlled": exp.scenario.estimator.controlled,
        "source": des.source,
        "gamma2": float(d["gamma2"]), "gamma2_bar": float(d["gamma2_bar"]),
        "nodes": {str(aid): i for i, aid in enumerate(exp.agent_ids)},
        "note": "lmi: the full design (estimation.hinf_lmi.design's dict; node i = agent index i); "
                "usable as estimator.design_cache",
        "lmi": d,
    }
