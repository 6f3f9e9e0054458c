"""Plugin: van der Horst, Chong, Kim, Sandberg -- the median of a bank of observers for Lur'e
plants, on a line of droop-controlled inverters; with the named plant ``inverters``.

``[plant] model = "inverters"`` is the line of N = 5 customers of Sections V-VI
(:class:`estimation.inverters.InverterNetwork`): state ``x = q_g`` (VAr), the Lur'e plant
(7) integrated with RK4 at ``dt`` (``params.substeps`` steps per round), known input
``v'_0(t) = 230 + v0_amplitude sin(v0_omega t)`` V, plant from ``q_g = 0``. The sensors
publish the customer **voltages in volts**, ``y_i = v_i`` (13), so a shared sensor attack
(``[[attacks]] kind = "constant", value = 30``) adds ``alpha_i = +30 V`` exactly as the
paper's attack does; the estimators map volts to the output of (7),
``y~_i = v_bar^2 - y_i^2`` (which turns ``alpha`` into ``a_i = -(2 v_i alpha_i + alpha_i^2)``).
``params.disturbance > 0`` switches on the random voltage disturbance ``|delta_i| <= it``
(V), independent per customer, piecewise constant, redrawn every ``params.hold`` s, seeded
from ``run.seed``; it enters ``z_i`` as ``d_i = v_bar^2 - (v_bar + delta_i)^2``, so both the
droop controllers and the sensors see it (eq. (7)). The plant defines the block ``v2``:
the matrix ``H``, so the monitor's ``error_inf`` on it is the squared-voltage error
``max_k |H_k (x - x_hat)|`` in V^2 of (36).

``[estimator] algorithm = "median_bank"`` with ``mode``:

* ``"median"`` -- the paper: one agent (the substation) reads every sensor, runs observer
  (9) per sensor and fuses by the componentwise median (5);
* ``"conventional"`` -- observer (16) on all sensors (non-resilient comparison);
* ``"static_inversion"`` -- ``x_hat = H^-1 (y~ - w(t))`` (reference);
* ``"distributed"`` -- every agent reads its own sensor and runs its own observer (9);
  the team agrees on the componentwise median of their estimates with the sign-based
  distributed median solver (:mod:`estimation.distributed_median`, Lee-Kim-Shim eq. (4)
  with the Lur'e model as drift as in their eq. (6), gains ``kappa``, ``gamma``);
* ``"flooding"`` -- as ``"distributed"`` but the exact median by flooding (the reference).

The LMI design (10) of the bank and of (16) is done once per run in :func:`design`
(cvxpy + Clarabel); the result is plain arrays (picklable, written to ``design.json``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
from pydantic import Field

from estimation import graphs
from estimation.base import EstimatePayload
from estimation.batching import Batch, Batchable
from estimation.distributed_median import FloodingMedian, SignMedianAgent
from estimation.errors import DesignError, ScenarioError
from estimation.inverters import droop_slope_bound
from estimation.lure import LurePlant
from estimation.median_bank import (
    LureObserver,
    MedianBank,
    check_report,
    design_bank,
    design_conventional,
    static_inversion,
)
from estimation.median_solver import theorem1_bound

from ..common import STREAM_AGENT_X0, Condition, ThreatModel, estimator_section, rng_for
from ..helpers import init_vector
from ..types import Init, Strict
from .inverters_plant import ERROR_BLOCK as ERROR_BLOCK  # the error block of the runs (tests and scripts read it here)
from .inverters_plant import PLANTS as PLANTS  # the plugin contract's named plants
from .inverters_plant import LureDrift, ModelReference

if TYPE_CHECKING:
    from ..build import Experiment

MODES = ("median", "conventional", "static_inversion", "distributed", "flooding")
CENTRAL = ("median", "conventional", "static_inversion")


class MedianBankEstimator(Strict):
    """van der Horst et al.: observers (9) per sensor fused by the median (5), and variants."""

    algorithm: Literal["median_bank"]
    mode: Literal["median", "conventional", "static_inversion", "distributed", "flooding"] = "median"
    #: attack budget: sensors that may be attacked (N > 2M is required)
    M: int = Field(default=2, ge=0)
    #: gain rule of the LMI design: keep mu_d within (1 + slack) of its optimum
    slack: float = Field(default=1e-3, ge=0)
    #: pole-region bound of the conventional observer (16), 1/s; default 0.2 / dt
    conventional_max_rate: float | None = Field(default=None, gt=0)
    #: RK4 steps per round of every observer (and of the drift of the distributed modes)
    substeps: int = Field(default=1, ge=1)
    #: initial estimate of every observer; default Q_bar / 4 (the reference setting)
    x0: Init | None = None
    #: distributed: the sign gain (VAr/s) and the coupling (1/VAr) of the median solver
    kappa: float = Field(default=20.0, gt=0)
    gamma: float = Field(default=2.0, gt=0)
    #: distributed: the solver's drift: "model" = the Lur'e model at the agent's own value (as
    #: A x + B u in LKS eq. (6)); "reference" = the motion of the model run open loop from
    #: Q_bar / 4 (the same at every agent); "none" = eq. (4) as printed
    drift: Literal["model", "reference", "none"] = "model"
    #: distributed: discretisation of the sgn term
    sign: Literal["implicit", "held"] = "implicit"
    #: distributed: neighbour values older than this many rounds are not used
    max_age: int = Field(default=3, ge=0)
    #: flooding: move stale rows to the current round with the model (open loop)
    predict: bool = True


ESTIMATOR = MedianBankEstimator
THREAT_MODEL = ThreatModel(sensors="M")  # at most M attacked sensors


def _section(exp: "Experiment") -> MedianBankEstimator:
    """This plugin's ``[estimator]`` section of ``exp``, typed."""
    return estimator_section(exp, MedianBankEstimator)





# --------------------------------------------------------------------------- design
@dataclass(frozen=True)
class MedianBankDesign:
    """The offline design: plain arrays, picklable.

    ``bank``: :func:`estimation.median_bank.design_bank` (observer (9) per sensor);
    ``conventional``: :func:`estimation.median_bank.design_conventional` (16); ``None``
    where the LMI failed (``errors`` says why). A run fails on the design its mode needs;
    ``rse check`` (``check = False``) reports it instead.
    """

    bank: dict | None
    conventional: dict | None
    max_rate: float
    errors: dict[str, str] = field(default_factory=dict)


def _lure_stepper(exp: "Experiment") -> Any:
    st = exp.stepper
    if st is None or not hasattr(st, "lure") or not hasattr(st, "to_lure_output"):
        raise ScenarioError(f"estimator.algorithm: 'median_bank' needs a Lur'e plant (plant.model = 'inverters'), "
                            f"got {exp.scenario.plant.model!r}", source=exp.source)
    return st


def _sensors(exp: "Experiment", i: int) -> np.ndarray:
    """0-based sensor ids agent ``i`` reads, in the order of its measurement (one row each)."""
    return np.asarray(exp.agent_rows[i], dtype=int)


def _check_agents(exp: "Experiment") -> None:
    est = _section(exp)
    N = exp.plant.C.shape[0]
    if not exp.static:
        raise ScenarioError("estimator.algorithm: 'median_bank' needs static agents ([[agents]] with sensors)", source=exp.source)
    for i in range(exp.N):
        s = _sensors(exp, i)
        if est.mode in CENTRAL and sorted(s.tolist()) != list(range(N)):
            raise ScenarioError(f"agents[{i}].sensors: mode {est.mode!r} is central: agent {exp.agent_ids[i]} must read "
                                f"every sensor 1..{N}, got {[int(v) + 1 for v in s]}", source=exp.source)
        if est.mode not in CENTRAL and len(s) != 1:
            raise ScenarioError(f"agents[{i}].sensors: mode {est.mode!r}: every agent reads its own sensor (one), agent "
                                f"{exp.agent_ids[i]} reads {[int(v) + 1 for v in s]}", source=exp.source)


def _n_values(exp: "Experiment") -> int:
    """How many estimates the median is taken over: sensors (central) or agents (distributed)."""
    return exp.plant.C.shape[0] if _section(exp).mode in CENTRAL else exp.N


def design(exp: "Experiment", *, check: bool = True) -> MedianBankDesign:
    est = _section(exp)
    st = _lure_stepper(exp)
    _check_agents(exp)
    if check and est.mode in ("median", "distributed", "flooding") and not _n_values(exp) > 2 * est.M:
        raise ScenarioError(f"estimator.M: the median needs N > 2M, got N = {_n_values(exp)}, M = {est.M}", source=exp.source)
    max_rate = est.conventional_max_rate if est.conventional_max_rate is not None else 0.2 / exp.dt
    needs = {"median": "bank", "distributed": "bank", "flooding": "bank", "conventional": "conventional"}.get(est.mode)
    out: dict[str, Any] = {"bank": None, "conventional": None}
    errors: dict[str, str] = {}
    for key, fn in (("bank", lambda: design_bank(st.lure, slack=est.slack)),
                    ("conventional", lambda: design_conventional(st.lure, max_rate=max_rate, slack=est.slack))):
        try:
            out[key] = fn()
        except DesignError as exc:
            if check and key == needs:
                raise ScenarioError(f"estimator: {exc}", source=exp.source) from None
            errors[key] = str(exc)
    return MedianBankDesign(bank=out["bank"], conventional=out["conventional"], max_rate=float(max_rate), errors=errors)


# --------------------------------------------------------------------------- estimators
class CentralEstimator(Batchable):
    """The substation: one estimator reading every sensor (modes median, conventional,
    static_inversion). ``estimates`` is the bank's ``(N, n)`` in the median mode.
    Batchable: the median mode steps its bank as one stacked state (:mod:`.inverters_batch`)."""

    def batch_key(self) -> tuple:
        return (CentralEstimator, self.mode, id(self._lure), self._dt)

    @classmethod
    def batch(cls, members, **kw) -> Batch:
        from .inverters_batch import BankBatch, SerialBatch

        return (BankBatch if members[0].mode == "median" else SerialBatch)(members, **kw)

    def __init__(self, mode: str, lure: LurePlant, *, order: np.ndarray, dt: float, x0: np.ndarray,
                 bank: dict | None, conventional: dict | None, to_lure, M: int, substeps: int) -> None:
        self.mode, self._lure, self._dt, self._map = mode, lure, float(dt), to_lure
        self._perm = np.argsort(order)  # measurement (agent order) -> sensor order
        self._x = np.array(x0, dtype=float)
        self._core: MedianBank | LureObserver | None
        if mode == "median":
            if bank is None:
                raise ValueError("the median mode needs its bank design")
            self._core = MedianBank(lure, bank=bank, dt=dt, x0=x0, n_attacked=M, substeps=substeps, measurement_map=to_lure)
        elif mode == "conventional":
            if conventional is None:
                raise ValueError("the conventional mode needs its gains")
            self._core = LureObserver(lure, sensors=range(lure.N), L=conventional["L"], K=conventional["K"], dt=dt, x0=x0,
                                      substeps=substeps, measurement_map=to_lure)
        else:
            self._core = None

    @property
    def estimate(self) -> np.ndarray:
        return self._x.copy()

    @property
    def estimates(self) -> np.ndarray:
        """The bank's estimates ``(N, n)`` (median mode only)."""
        if not isinstance(self._core, MedianBank):
            raise AttributeError("estimates: only the median mode has a bank")
        return self._core.estimates

    def step(self, k: int, measurement: np.ndarray | None, inbox: Any = None) -> np.ndarray:
        y = None if measurement is None else np.asarray(measurement, dtype=float)[self._perm]
        if self._core is not None:
            self._x = np.asarray(self._core.step(k, y), dtype=float)
        elif y is not None:
            self._x = static_inversion(self._lure, k * self._dt, self._map(y))
        return self._x.copy()


def _valid(value: Any, size: int) -> bool:
    v = np.asarray(value)
    return v.shape == (size,) and bool(np.all(np.isfinite(v)))


class DistributedMedianEstimator(Batchable, EstimatePayload):
    """One inverter (mode distributed): its own observer (9) on its own sensor, and the
    sign-based distributed median of the team's estimates. Publishes and reports ``xi_i``;
    ``local_estimate`` is its observer's ``x_hat^i``. Neighbour messages that are not a
    finite ``(n,)`` array are ignored. Batchable (:mod:`.inverters_batch`)."""

    def batch_key(self) -> tuple:
        o, kw = self._obs, self._solver._kw
        drift = "model" if isinstance(kw["drift"], LureDrift) else ("reference" if self._solver._ref else "none")
        return (DistributedMedianEstimator, id(o._plant), o._dt, o._substeps, kw["kappa"], kw["gamma"], kw["sign"],
                drift, self._solver.max_age)

    @classmethod
    def batch(cls, members, **kw) -> Batch:
        from .inverters_batch import DistributedBatch

        return DistributedBatch(members, **kw)

    def __init__(self, lure: LurePlant, *, sensor: int, bank: dict, dt: float, x0: np.ndarray, to_lure, substeps: int,
                 kappa: float, gamma: float, drift: str, sign: str, max_age: int, reference_x0: np.ndarray) -> None:
        self.n = lure.n
        self._obs = LureObserver(lure, sensors=[sensor], L=bank["L"][sensor], K=bank["K"][sensor], dt=dt, x0=x0,
                                 substeps=substeps, measurement_map=to_lure)
        ref = ModelReference(lure, x0=reference_x0, dt=dt, substeps=substeps) if drift == "reference" else None
        self._solver = SignMedianAgent(n=lure.n, kappa=kappa, gamma=gamma, dt=dt,
                                       drift=LureDrift(lure) if drift == "model" else None, reference=ref,
                                       substeps=substeps, sign=sign, max_age=max_age)
        self._local = np.array(x0, dtype=float)

    @property
    def estimate(self) -> np.ndarray:
        return self._solver.estimate

    @property
    def local_estimate(self) -> np.ndarray:
        return self._local.copy()

    def step(self, k: int, measurement: np.ndarray | None, inbox: Any = None) -> np.ndarray:
        self._local = self._obs.step(k, measurement)
        clean = {j: r for j, r in (inbox or {}).items() if _valid(r.value, self.n)}
        return self._solver.step(k, self._local, clean)


class FloodingEstimator:
    """One inverter (mode flooding): its own observer (9) and the exact median by flooding.
    The payload is the flooding table (``N (n + 1)`` floats); ``estimate`` the median."""

    def __init__(self, lure: LurePlant, *, agent: int, N: int, sensor: int, bank: dict, dt: float, x0: np.ndarray,
                 to_lure, substeps: int, predict: bool) -> None:
        self._obs = LureObserver(lure, sensors=[sensor], L=bank["L"][sensor], K=bank["K"][sensor], dt=dt, x0=x0,
                                 substeps=substeps, measurement_map=to_lure)
        self._flood = FloodingMedian(agent=agent, N=N, n=lure.n, dt=dt, drift=LureDrift(lure), substeps=substeps,
                                     predict=predict)
        self._local = np.array(x0, dtype=float)

    @property
    def estimate(self) -> np.ndarray:
        return self._flood.estimate

    @property
    def local_estimate(self) -> np.ndarray:
        return self._local.copy()

    def step(self, k: int, measurement: np.ndarray | None, inbox: Any = None) -> np.ndarray:
        self._local = self._obs.step(k, measurement)
        return self._flood.step(k, self._local, inbox)


def _x0(exp: "Experiment", i: int, st: Any) -> np.ndarray:
    spec = _section(exp).x0
    if spec is None:
        return np.asarray(st.params.Q_bar, dtype=float) / 4.0
    return init_vector(spec, exp.n, rng_for(exp.seed, STREAM_AGENT_X0, i), where="estimator.x0")


def make_estimator(exp: "Experiment", i: int):
    est, st, des = _section(exp), _lure_stepper(exp), exp.design
    x0 = _x0(exp, i, st)
    if est.mode in CENTRAL:
        return CentralEstimator(est.mode, st.lure, order=_sensors(exp, i), dt=exp.dt, x0=x0, bank=des.bank,
                                conventional=des.conventional, to_lure=st.to_lure_output, M=est.M, substeps=est.substeps)
    sensor = int(_sensors(exp, i)[0])
    if est.mode == "distributed":
        return DistributedMedianEstimator(st.lure, sensor=sensor, bank=des.bank, dt=exp.dt, x0=x0, to_lure=st.to_lure_output,
                                          substeps=est.substeps, kappa=est.kappa, gamma=est.gamma, drift=est.drift,
                                          sign=est.sign, max_age=est.max_age,
                                          reference_x0=np.asarray(st.params.Q_bar, dtype=float) / 4.0)
    return FloodingEstimator(st.lure, agent=i, N=exp.N, sensor=sensor, bank=des.bank, dt=exp.dt, x0=x0,
                             to_lure=st.to_lure_output, substeps=est.substeps, predict=est.predict)


# --------------------------------------------------------------------------- rse check
def conditions(exp: "Experiment") -> list[Condition]:
    """Slope bound (Assumption 3), the LMI (10) per observer (feasible, mu_d), N > 2M, and
    for the distributed modes the solver's figures."""
    est = _section(exp)
    out: list[Condition] = []
    try:
        st = _lure_stepper(exp)
    except ScenarioError as exc:
        return [Condition("Lur'e plant", False, exc.detail)]
    p = st.params
    slopes = droop_slope_bound(Q_bar=p.Q_bar, w_min=p.w_min, w_m=p.w_m, w_n=p.w_n, w_max=p.w_max)
    out.append(Condition("droop slopes <= e_bar (Assumption 3)", bool(np.all(slopes <= p.e_bar * (1 + 1e-6))),
                         f"max slope {slopes.max():.6g} VAr/V^2, e_bar = {p.e_bar:g}"))
    des = exp.design
    if des is None:
        try:
            des = design(exp, check=False)
        except ScenarioError as exc:
            return out + [Condition("LMI (10) feasible for every observer (Proposition 1)", False, exc.detail)]
    n_vals = _n_values(exp)
    if des.bank is None:
        out.append(Condition("LMI (10) feasible for every observer (Proposition 1)", False, des.errors.get("bank", "")))
    else:
        rep = check_report(des.bank, n_attacked=est.M)
        out.append(Condition("LMI (10) feasible for every observer (Proposition 1)", rep["feasible"],
                             f"{len(rep['mu_d'])} observers, nu = 1, mu_a = mu_d, slack {est.slack:g}"))
        out.append(Condition("mu_d per observer (sensors 1..N)", None, ", ".join(f"{m:.4g}" for m in rep["mu_d"])))
        out.append(Condition("optimum mu_d* of (10) per observer", None, ", ".join(f"{m:.4g}" for m in rep["mu_d_opt"])))
    med = est.mode in ("median", "distributed", "flooding")
    what = "sensors" if est.mode in CENTRAL else "agents"
    out.append(Condition(f"N > 2M (median over {what})", bool(n_vals > 2 * est.M) if med else None,
                         f"N = {n_vals}, M = {est.M}"))
    if est.mode == "conventional":
        c = des.conventional
        if c is None:
            out.append(Condition("conventional observer (16): LMI (10) + pole region", False, des.errors.get("conventional", "")))
        else:
            eig = np.linalg.eigvals(st.lure.A - c["L"] @ st.lure.H)
            out.append(Condition("conventional observer (16): LMI (10) + pole region", bool(c["lmi_max_eig"] <= 1e-6 * max(1.0, c["mu_d"])),
                                 f"mu_d = {c['mu_d']:.4g}, max_rate = {des.max_rate:g}/s, dt |eig(A - L H)| max = {np.abs(eig).max() * exp.dt:.3g}"))
    if est.mode in ("distributed", "flooding"):
        Adj = exp.Adj
        connected = len(graphs.components(Adj)) == 1
        if est.mode == "distributed" and graphs.is_undirected(Adj) and connected and exp.N > 1:
            b = theorem1_bound(Adj, est.gamma)
            rows = float(np.abs(st.lure.H).sum(axis=1).max())
            out.append(Condition(f"solver bound 2 sqrt(N)/(gamma lambda_2), gamma = {est.gamma:g} (LKS Theorem 1)", None,
                                 f"{b:.4g} VAr (x max_k |H_k|_1 = {b * rows:.4g} V^2), for constant estimates"))
            cdt = est.kappa * est.gamma * int(Adj.sum(axis=1).max()) * exp.dt
            out.append(Condition("consensus step kappa gamma d_max dt (order 1 or less)", None, f"{cdt:.3g}"))
        if est.mode == "flooding":
            ecc = _diameter(Adj)
            out.append(Condition("flooding: rounds until every row is known (diameter)", connected, f"{ecc}"))
    return out


def _diameter(Adj: np.ndarray) -> int | None:
    N = Adj.shape[0]
    D = np.where(np.asarray(Adj) > 0, 1.0, np.inf)
    np.fill_diagonal(D, 0.0)
    for k in range(N):
        D = np.minimum(D, D[:, k:k + 1] + D[k:k + 1, :])
    m = float(D.max())
    return int(m) if np.isfinite(m) else None


def design_json(exp: "Experiment") -> dict:
    d = exp.design
    if d is None:
        return {}
    st = _lure_stepper(exp)
    keys = ("L", "K", "P", "U", "mu_d", "mu_a", "mu_d_opt", "lmi_max_eig")
    return {
        "mode": _section(exp).mode,
        "M": _section(exp).M,
        "bank": None if d.bank is None else {k: d.bank[k] for k in keys + ("slack",)},
        "conventional": None if d.conventional is None else {k: d.conventional[k] for k in keys + ("max_rate",)},
        "errors": d.errors,
        "plant": {"H": st.lure.H, "A": st.lure.A, "slope_upper": st.lure.slope_upper,
                  "disturbance_V": st.disturbance, "hold_s": st.hold},
    }
