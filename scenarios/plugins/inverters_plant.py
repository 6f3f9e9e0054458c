"""The inverter bank's plant (:mod:`scenarios.plugins.inverters`): the Lur'e drift (7), the
model reference and the ZOH stepper of the ``inverters`` plant model."""


from typing import TYPE_CHECKING

import numpy as np

from estimation.errors import ScenarioError
from estimation.inverters import InverterNetwork, InverterParams, random_voltage_disturbance
from estimation.lti import ContinuousLTI
from estimation.lure import LurePlant

from ..common import STREAM_PLANT_NOISE, PlantModel, rng_for
from ..helpers import check_size, plant_params

if TYPE_CHECKING:
    from ..schema import Scenario

#: the squared-voltage error block (matrix H of (7)), V^2
ERROR_BLOCK = "v2"


# --------------------------------------------------------------------------- the plant
class LureDrift:
    """``f(t, X) = X A' + phi(X H' + w(t)) G'``: the Lur'e model (7) for one state ``(n,)``
    or a stack of states ``(m, n)`` (the drift of the distributed median)."""

    def __init__(self, plant: LurePlant) -> None:
        self._p = plant

    def __call__(self, t: float, X: np.ndarray) -> np.ndarray:
        p = self._p
        return X @ p.A.T + p.phi(X @ p.H.T + p.w(t)) @ p.G.T


class ModelReference:
    """``r(k)``: the Lur'e model (7) run open loop (``d = 0``, no injection) from ``x0`` with
    RK4 at ``dt``; every agent computes the same values (the common reference of
    :class:`estimation.distributed_median.SignMedianAgent`)."""

    def __init__(self, plant: LurePlant, *, x0: np.ndarray, dt: float, substeps: int = 1) -> None:
        self._p, self._x0, self._dt, self._sub = plant, np.array(x0, dtype=float), float(dt), int(substeps)
        self._at: tuple[int, np.ndarray] = (0, self._x0.copy())
        self._before: tuple[int, np.ndarray] | None = None  # the value one round earlier

    def __call__(self, k: int) -> np.ndarray:
        j, x = self._at
        if self._before is not None and k == self._before[0]:
            return self._before[1].copy()
        if k < j:
            j, x = 0, self._x0.copy()
        while j < k:
            self._before = (j, x)
            x = self._p.step(j * self._dt, x, self._dt, substeps=self._sub)
            j += 1
        self._at = (j, x)
        return x.copy()


class InverterStepper:
    """The inverter line as a plant stepper (:class:`scenarios.common.PlantStepper`).

    ``measure(k, x)`` returns the customer voltages in V, ``v = sqrt(v_bar^2 - z)`` with
    ``z = H x + w(t_k) + d[k]``; ``advance(k, x)`` is ``substeps`` RK4 steps of (7) over
    ``[t_k, t_k + dt)`` with ``w`` evaluated and ``d[k]`` held (the reference loop
    :func:`estimation.median_bank.run_central` does exactly this). Picklable: the network
    (which holds closures) is rebuilt from ``params`` after unpickling.
    """

    def __init__(self, params: InverterParams, *, dt: float, disturbance: float = 0.0, hold: float = 0.1,
                 noise_seed: int = 0, substeps: int = 1) -> None:
        self.params, self.dt = params, float(dt)
        self.disturbance, self.hold, self.noise_seed = float(disturbance), float(hold), int(noise_seed)
        self.substeps = int(substeps)
        self._setup()

    def _setup(self) -> None:
        self.net = InverterNetwork(self.params)
        self._delta = (random_voltage_disturbance(N=self.net.N, seed=self.noise_seed, bound=self.disturbance,
                                                  hold=self.hold) if self.disturbance > 0 else None)
        self._dk: tuple[int, np.ndarray] | None = None

    def __getstate__(self) -> dict:
        return {k: v for k, v in self.__dict__.items() if k in ("params", "dt", "disturbance", "hold", "noise_seed", "substeps")}

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._setup()

    @property
    def lure(self) -> LurePlant:
        """The Lur'e plant (7) in ``x = q_g``, ``z = v_bar^2 - v^2``."""
        return self.net.plant

    def to_lure_output(self, y_volts: np.ndarray) -> np.ndarray:
        """Published voltages (13) to the output of (7), ``y~ = v_bar^2 - y^2`` (V^2)."""
        return self.net.lure_output(y_volts)

    def d(self, k: int) -> np.ndarray:
        """``d[k]`` in the coordinates of (7) (V^2), zeros without disturbance."""
        if self._delta is None:
            return np.zeros(self.net.N)
        if self._dk is None or self._dk[0] != k:
            self._dk = (k, self.net.squared_disturbance(self._delta(k * self.dt)))
        return self._dk[1]

    def measure(self, k: int, x: np.ndarray) -> np.ndarray:
        z = self.lure.z(k * self.dt, np.asarray(x, dtype=float), self.d(k))
        return np.sqrt(self.params.v_bar**2 - z)

    def advance(self, k: int, x: np.ndarray) -> np.ndarray:
        return self.lure.step(k * self.dt, np.asarray(x, dtype=float), self.dt, d=self.d(k), substeps=self.substeps)


_INVERTERS = {"disturbance": 0.0, "hold": 0.1, "substeps": 1.0, "v0_amplitude": 5.0, "v0_omega": 1.0}


def _inverter_plant(sc: "Scenario", source: str) -> PlantModel:
    pl = sc.plant
    if pl.A is not None or pl.B is not None:
        raise ScenarioError("plant: A and B are given by model 'inverters'", source=source)
    if pl.time == "discrete":
        raise ScenarioError("plant.time: model 'inverters' is a continuous-time plant", source=source)
    if sc.sensors is not None:
        raise ScenarioError("sensors: the sensors (customer voltages) are given by model 'inverters'", source=source)
    p = plant_params(pl, _INVERTERS, source, integers={"substeps": (1, None)})
    check_size("substeps", p["substeps"], "plant.params.substeps", run=sc.run, source=source)
    if p["disturbance"] < 0:
        raise ScenarioError(f"plant.params.disturbance: expected a bound >= 0 (V), got {p['disturbance']}", source=source)
    if not p["hold"] > 0:
        raise ScenarioError(f"plant.params.hold: expected a period > 0 (s), got {p['hold']}", source=source)
    params = InverterParams(v0_amplitude=p["v0_amplitude"], v0_omega=p["v0_omega"])
    seed = int(rng_for(sc.run.seed, STREAM_PLANT_NOISE).integers(2**31 - 1))
    stepper = InverterStepper(params, dt=sc.run.dt, disturbance=p["disturbance"], hold=p["hold"], noise_seed=seed,
                              substeps=p["substeps"])
    lure = stepper.lure
    n = lure.n
    if pl.state_names and len(pl.state_names) != n:
        raise ScenarioError(f"plant.state_names: expected {n} names, got {len(pl.state_names)}", source=source)
    names = tuple(pl.state_names) if pl.state_names else tuple(f"q_g{i + 1}" for i in range(n))
    # linear part and output rows (z = H x + w): shapes and the LTI view; the stepper is the plant
    lti = ContinuousLTI(A=np.array(lure.A), B=np.zeros((n, 0)), banks=tuple(lure.H[i:i + 1].copy() for i in range(lure.N)),
                        state_names=names)
    return PlantModel(lti=lti, discrete=False, x0=np.zeros(n), blocks={ERROR_BLOCK: np.array(lure.H)}, stepper=stepper,
                      substeps=p["substeps"])


PLANTS = {"inverters": (_INVERTERS, _inverter_plant)}
