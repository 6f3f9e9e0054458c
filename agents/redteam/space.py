"""The search space of a red-team search, derived from a scenario's threat model.

A *candidate* is plain data (JSON-able) and turns into ``--set`` overrides of the scenario
file, so that the worst candidate is simply the scenario with those overrides frozen::

    {"sensor": [{"bank": 1, "kind": "sine", "size": 1.04, "start": 10.0, "omega": 11.7, "phase": 0.0}],
     "agent": [{"agent": 5, "kind": "constant", "start": 0.0, "value": 3.0}],
     "channel": {"drop_p": 0.3, "seed": 17, "losses": [{"link": [1, 2], "start": 40, "length": 10}]}}

The threat model is what the algorithm's plugin declares (``THREAT_MODEL``, a
:class:`scenarios.helpers.ThreatModel`; docs/redteam.md): Lee-Kim-Shim tolerates
``estimator.q`` attacked sensor banks, van der Horst et al. ``estimator.M``, Mao-Tabuada
``estimator.s``; Mitra et al. ``estimator.f`` Byzantine agents in any neighbourhood; every
algorithm erasures up to the scenario's ``network.channel.drop_p``. A third-party plugin
declares its own. A ``[redteam]`` table narrows or widens the derived space; a budget above
the threat model is an error without ``beyond``.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from estimation.errors import ScenarioError
from estimation.lti import dense

if TYPE_CHECKING:
    from scenarios.build import Experiment

__all__ = ["MetricSpec", "Space", "derive", "METRICS", "SENSOR_KINDS", "AGENT_KINDS", "active_components"]

METRICS = ("error_2", "error_inf", "relative_error_2", "error_ratio")
SENSOR_KINDS = ("constant", "ramp", "sine", "random", "trajectory")
AGENT_KINDS = ("constant", "huge", "omission", "equivocation", "false_stamp", "replay", "crash", "cancellation")


@dataclass(frozen=True)
class MetricSpec:
    """The maximised quantity: the worst regular agent's ``metric`` over ``over`` in ``block``."""

    metric: str = "error_inf"
    over: Any = "window"  # "window", "final" or (t0, t1)
    block: str = "x"

    def label(self) -> str:
        over = self.over if isinstance(self.over, str) else f"t in [{self.over[0]:g}, {self.over[1]:g}]"
        block = "any block" if self.block == "all" else f"block {self.block}"
        return f"max {self.metric} (worst regular agent, {block}, {over})"

    def expect_table(self, threshold: float | None) -> dict[str, Any]:
        """An ``[[expect]]`` table that prints this metric when the scenario runs."""
        t: dict[str, Any] = {"label": f"red-team metric: {self.label()}", "metric": self.metric, "block": self.block,
             "over": self.over if isinstance(self.over, str) else list(self.over)}
        if threshold is not None:
            t["max"] = float(threshold)
        else:
            t["min"] = 0.0
        return t


@dataclass
class Space:
    """What one candidate may contain; :meth:`sample` draws one from an Optuna trial."""

    algorithm: str
    q: int | None  # the threat model's sensor budget (None: sensors are honest in this model)
    f: int | None  # Byzantine agents per neighbourhood (None: agents are trusted in this model)
    p: float  # the scenario's erasure probability
    beyond: bool
    sensors: int = 0
    banks: list[int] = field(default_factory=list)
    kinds: list[str] = field(default_factory=list)
    amplitude: float = 1.0
    omega: tuple[float, float] = (0.0, 1.0)
    start: tuple[float, float] = (0.0, 0.0)
    horizon: float = 1.0  # seconds
    agents: int = 0
    candidates: list[int] = field(default_factory=list)
    strategies: list[str] = field(default_factory=list)
    value: float = 1e6
    drop_p: float = 0.0
    seed: bool = False
    losses: int = 0
    loss_length: int = 1
    links: list[tuple[int, int]] = field(default_factory=list)
    rounds: int = 1
    dt: float = 1.0
    #: an LTI plant's (Ad, C, x0, bank rows) for dynamics-consistent ("trajectory") candidates
    lti: dict[str, Any] | None = field(default=None, repr=False)
    kept_attacks: list[dict] = field(default_factory=list)  # the scenario's attacks of targets not searched
    own: list[Any] = field(default_factory=list, repr=False)  # the scenario's own attacks (validated models)
    base_seed: int = 0  # the scenario's run.seed
    base_losses: list[dict] = field(default_factory=list)

    @property
    def empty(self) -> bool:
        return self.sensors == 0 and self.agents == 0 and self.drop_p == 0 and self.losses == 0

    def describe(self) -> dict[str, Any]:
        d: dict[str, Any] = {"threat_model": {"q": self.q, "f": self.f, "drop_p": self.p}, "beyond": self.beyond}
        if self.sensors:
            d["sensors"] = {"count": self.sensors, "banks": self.banks, "kinds": self.kinds,
                            "amplitude": self.amplitude, "omega": list(self.omega), "start": list(self.start)}
        if self.agents:
            d["agents"] = {"count": self.agents, "candidates": self.candidates, "strategies": self.strategies,
                           "value": self.value, "start": list(self.start)}
        if self.drop_p > 0 or self.losses:
            d["channel"] = {"drop_p": [0.0, self.drop_p] if self.drop_p > 0 else None, "seed": self.seed,
                            "losses": self.losses, "loss_length": self.loss_length}
        return d

    # ------------------------------------------------------------------ sampling
    def sample(self, trial: Any) -> dict[str, Any]:
        """One candidate from an Optuna trial (define-by-run: a kind's own parameters are
        conditional on the kind)."""
        cand: dict[str, Any] = {"sensor": [], "agent": [], "channel": {}}
        for s in range(self.sensors):
            kind = trial.suggest_categorical(f"s{s}_kind", self.kinds)
            att = {"bank": trial.suggest_categorical(f"s{s}_bank", self.banks), "kind": kind,
                   "size": trial.suggest_float(f"s{s}_size", -self.amplitude, self.amplitude),
                   "start": trial.suggest_float(f"s{s}_start", *self.start)}
            if kind == "sine":
                att["omega"] = trial.suggest_float(f"s{s}_omega", *self.omega)
                att["phase"] = trial.suggest_float(f"s{s}_phase", 0.0, 2 * math.pi)
            elif kind == "trajectory":
                att["direction"] = [trial.suggest_float(f"s{s}_d{j}", -1.0, 1.0) for j in range(len(self._lti()["x0"]))]
            cand["sensor"].append(att)
        used: set[int] = set()
        for a in range(self.agents):
            agent = trial.suggest_categorical(f"a{a}_agent", self.candidates)
            kind = trial.suggest_categorical(f"a{a}_kind", self.strategies)
            att = {"agent": agent, "kind": kind, "start": trial.suggest_float(f"a{a}_start", *self.start)}
            if kind == "constant":
                att["value"] = trial.suggest_float(f"a{a}_value", -self.value, self.value)
            elif kind in ("huge", "equivocation"):
                att["scale"] = trial.suggest_float(f"a{a}_scale", min(1e-3, self.value), self.value, log=True)
            elif kind == "false_stamp":
                att["shift"] = trial.suggest_int(f"a{a}_shift", 1, 10) * (
                    1 if trial.suggest_categorical(f"a{a}_future", [True, False]) else -1)
                att["payload"] = trial.suggest_categorical(f"a{a}_payload", ["estimate", "huge"])
            elif kind == "replay":
                att["lag"] = trial.suggest_int(f"a{a}_lag", 1, 50)
            if agent not in used:  # one strategy per agent: a repeated agent leaves the slot empty
                used.add(agent)
                cand["agent"].append(att)
        ch: dict[str, Any] = {}
        if self.drop_p > 0:
            ch["drop_p"] = trial.suggest_float("drop_p", 0.0, self.drop_p)
            if self.seed:
                ch["seed"] = trial.suggest_int("seed", 0, 2**31 - 1)
        if self.losses:
            ch["losses"] = []
            for w in range(self.losses):
                link = self.links[trial.suggest_int(f"w{w}_link", 0, len(self.links) - 1)]
                ch["losses"].append({"link": list(link), "start": trial.suggest_int(f"w{w}_start", 0, self.rounds),
                                     "length": trial.suggest_int(f"w{w}_length", 1, self.loss_length)})
        cand["channel"] = ch
        return cand

    # ------------------------------------------------------------------ overrides
    def attack_tables(self, cand: dict[str, Any]) -> list[dict[str, Any]]:
        out = [dict(a) for a in self.kept_attacks]
        for s in cand["sensor"]:
            t: dict[str, Any] = {"target": "sensor", "sensors": [int(s["bank"])], "kind": s["kind"], "start": float(s["start"])}
            size = float(s["size"])
            if s["kind"] == "constant":
                t["value"] = size
            elif s["kind"] == "ramp":  # reaches `size` at the horizon: |a| <= amplitude
                t["slope"] = size / max(self.horizon - float(s["start"]), self.dt)
            elif s["kind"] == "sine":
                t.update(amplitude=size, omega=float(s["omega"]), phase=float(s["phase"]))
            elif s["kind"] == "random":
                t["scale"] = abs(size)
            elif s["kind"] == "trajectory":
                t["x0_attack"] = self.trajectory_x0(int(s["bank"]), s["direction"], size)
            out.append(t)
        for a in cand["agent"]:
            t = {"target": "agent", "agents": [int(a["agent"])], "kind": a["kind"], "start": float(a["start"])}
            for key in ("value", "scale"):
                if key in a:
                    t[key] = float(a[key])
            for key in ("shift", "lag"):
                if key in a:
                    t[key] = int(a[key])
            if "payload" in a:
                t["payload"] = a["payload"]
            out.append(t)
        return out

    def trajectory_x0(self, bank: int, direction: list[float], size: float) -> list[float]:
        """``x0_attack = x0 + d`` with ``d`` along ``direction``, scaled so that the attack on
        ``bank``, ``C Ad^k d`` (Mao, Tabuada's dynamics-consistent attack), peaks at ``|size|``
        over the horizon."""
        lti = self._lti()
        u = np.asarray(direction, dtype=float)
        C = lti["C"][lti["rows"][bank - 1]]
        peak, v = 0.0, u.copy()
        for _ in range(self.rounds + 1):
            peak = max(peak, float(np.max(np.abs(C @ v))))
            v = lti["Ad"] @ v
        d = u * (abs(size) / peak) if peak > 0 and math.isfinite(peak) else np.zeros_like(u)
        return [float(x) for x in lti["x0"] + d]

    def _lti(self) -> dict[str, Any]:
        """The LTI data of the ``trajectory`` kind (set by :func:`derive` when it is searched)."""
        if self.lti is None:
            raise RuntimeError("the trajectory kind needs the LTI data of the space (derive sets it)")
        return self.lti

    def overrides(self, cand: dict[str, Any]) -> list[str]:
        """``KEY=VALUE`` strings (TOML values) that turn the scenario into this candidate."""
        ov = ["attacks=" + inline(self.attack_tables(cand))]
        ch = cand.get("channel", {})
        if "drop_p" in ch:
            ov.append(f"network.channel.drop_p={float(ch['drop_p'])!r}")
        if "seed" in ch:
            ov.append(f"run.seed={int(ch['seed'])}")
        if "losses" in ch:
            wins = [dict(w) for w in self.base_losses]
            for w in ch["losses"]:
                r0 = int(w["start"])
                wins.append({"rounds": [r0, r0 + int(w["length"]) - 1], "links": [list(map(int, w["link"]))]})
            ov.append("network.channel.losses=" + inline(wins))
        return ov


def active_components(cand: dict[str, Any]) -> int:
    """Attacked sensors + Byzantine agents + loss windows + (1 if erasures are on)."""
    ch = cand.get("channel", {})
    return len(cand["sensor"]) + len(cand["agent"]) + len(ch.get("losses", [])) + int(ch.get("drop_p", 0.0) > 0)


def inline(v: Any) -> str:
    """A value as TOML inline text (floats exactly, ``inf`` as TOML's ``inf``)."""
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k} = {inline(x)}" for k, x in v.items()) + "}"
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(inline(x) for x in v) + "]"
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        x = float(v)
        return ("inf" if x > 0 else "-inf") if math.isinf(x) else ("nan" if math.isnan(x) else repr(x))
    return json.dumps(str(v))


# ---------------------------------------------------------------------- derivation
def _bad(msg: str, source: str) -> ScenarioError:
    return ScenarioError(msg, source=source)


def _modal_band(exp: Experiment) -> tuple[float, float]:
    nyquist = math.pi / exp.dt
    if exp.discrete:
        return (0.0, nyquist)
    try:
        w = float(np.max(np.abs(np.linalg.eigvals(dense(exp.plant.A)).imag)))
    except (AttributeError, np.linalg.LinAlgError, ValueError):
        w = 0.0
    return (0.0, min(2.0 * w, nyquist) if w > 0 else nyquist)


def derive(exp: Experiment, *, beyond: bool = False, metric: str | None = None, over: Any = None, block: str | None = None
           ) -> tuple[Space, MetricSpec]:
    """The space and the metric for a built experiment (``[redteam]`` applied, validated)."""
    from scenarios import plugins
    from scenarios.schema import RedteamSection

    sc = exp.scenario
    src = exp.source
    rt = sc.redteam or RedteamSection()
    est = sc.estimator
    alg = est.algorithm
    tm = plugins.threat_model(alg)
    qkey, fkey = tm.sensors, tm.agents
    q = int(getattr(est, qkey)) if qkey else None
    f = int(getattr(est, fkey)) if fkey else None
    p = float(sc.network.channel.drop_p)
    T = exp.n_rounds * exp.dt
    sp = Space(algorithm=alg, q=q, f=f, p=p, beyond=beyond, horizon=T, rounds=exp.n_rounds, dt=exp.dt)

    # sensor attacks
    step = 1 if beyond else 0
    sp.sensors = rt.sensors if rt.sensors is not None else (q + step if q is not None else 0)
    if sp.sensors and not beyond:
        if q is None:
            raise _bad(f"redteam.sensors = {sp.sensors}: sensor attacks are outside {alg}'s threat model "
                       "(its sensors are trusted); pass --beyond to search them", src)
        if sp.sensors > q:
            raise _bad(f"redteam.sensors = {sp.sensors} is outside the threat model ({alg} tolerates "
                       f"estimator.{qkey} = {q} attacked banks); pass --beyond to search one step outside", src)
    nb = len(exp.bank_names)
    sp.banks = list(rt.banks) if rt.banks is not None else list(range(1, nb + 1))
    bad = [b for b in sp.banks if not 1 <= b <= nb]
    if bad:
        raise _bad(f"redteam.banks: no sensor bank {bad[0]}; banks are 1..{nb}", src)
    lti_ok = exp.stepper is None and exp.n <= 50
    sp.kinds = list(rt.kinds) if rt.kinds is not None else [k for k in SENSOR_KINDS if k != "trajectory" or lti_ok]
    if "trajectory" in sp.kinds:
        if exp.stepper is not None:
            raise _bad(f"redteam.kinds: 'trajectory' needs an LTI plant; model {sc.plant.model!r} has its own step", src)
        sp.lti = {"Ad": dense(exp.Ad), "C": np.asarray(exp.plant.C, dtype=float),
                  "x0": np.asarray(exp.x0, dtype=float), "rows": [np.asarray(r) for r in exp.bank_rows]}
    sizes = [abs(x) for a in sc.attacks if a.target == "sensor" for x in (a.value, a.amplitude, a.scale) if x]
    sp.amplitude = float(rt.amplitude if rt.amplitude is not None else (max(sizes) if sizes else 1.0))
    sp.omega = (rt.omega[0], rt.omega[1]) if rt.omega is not None else _modal_band(exp)
    w0 = min(exp.window[0], T)
    sp.start = (rt.start[0], rt.start[1]) if rt.start is not None else (0.0, w0)
    if sp.start[1] >= T:
        raise _bad(f"redteam.start: attacks must start before the horizon t = {T:g}, got {list(sp.start)}", src)

    # Byzantine agents
    sp.agents = rt.agents if rt.agents is not None else (f + step if f is not None else 0)
    if sp.agents and not beyond:
        if f is None:
            raise _bad(f"redteam.agents = {sp.agents}: Byzantine agents are outside {alg}'s threat model; "
                       "pass --beyond to search them", src)
        if sp.agents > f:
            raise _bad(f"redteam.agents = {sp.agents} is outside the threat model (at most estimator.f = {f} "
                       "Byzantine agents in any neighbourhood); pass --beyond to search one step outside", src)
    sp.candidates = list(rt.candidates) if rt.candidates is not None else list(exp.agent_ids)
    bad = [a for a in sp.candidates if a not in exp.agent_ids]
    if bad:
        raise _bad(f"redteam.candidates: no agent {bad[0]}; agents are {exp.agent_ids[0]}..{exp.agent_ids[-1]}", src)
    if sp.agents > len(sp.candidates):
        raise _bad(f"redteam.agents = {sp.agents} exceeds the {len(sp.candidates)} candidate agent(s)", src)
    allowed = list(tm.strategies) if tm.strategies is not None else list(AGENT_KINDS)
    sp.strategies = list(rt.strategies) if rt.strategies is not None else allowed
    outside = [k for k in sp.strategies if k not in allowed]
    if outside and sp.agents and not beyond:
        raise _bad(f"redteam.strategies: {outside[0]!r} is outside {alg}'s threat model (its strategies: "
                   f"{', '.join(allowed)}); pass --beyond to search it", src)
    sp.value = float(rt.value)

    # channel
    sp.drop_p = float(rt.drop_p) if rt.drop_p is not None else p
    if sp.drop_p > p and not beyond:
        raise _bad(f"redteam.drop_p = {sp.drop_p:g} is outside the threat model (erasures up to "
                   f"network.channel.drop_p = {p:g}); pass --beyond to search beyond it", src)
    sp.seed = bool(rt.seed)
    sp.losses, sp.loss_length = rt.losses, rt.loss_length
    A = np.asarray(exp.Adj)
    sp.links = [(exp.agent_ids[j], exp.agent_ids[i]) for i, j in zip(*np.nonzero(A)) if i != j]
    if sp.losses and not sp.links:
        raise _bad("redteam.losses: the graph has no links", src)
    sp.base_losses = [{"rounds": list(w.rounds), "links": [list(x) for x in w.links]} for w in sc.network.channel.losses]
    searched = {"sensor"} if sp.sensors else set()
    if sp.agents:
        searched.add("agent")
    sp.own, sp.base_seed = list(sc.attacks), int(sc.run.seed)
    sp.kept_attacks = [_plain(a.model_dump(exclude_defaults=True) | {"target": a.target}) for a in sc.attacks
                       if a.target not in searched]
    if sp.empty:
        raise _bad(f"empty search space: {alg} declares no sensor or Byzantine budget here and the channel has no "
                   "erasures; set [redteam] sensors / agents / drop_p / losses (with --beyond outside the threat model)",
                   src)

    # the metric
    lfre = alg == "lfre"
    name = metric or rt.metric or ("relative_error_2" if lfre else "error_inf")
    if name not in METRICS:
        raise _bad(f"--metric: unknown metric {name!r}; expected one of {', '.join(METRICS)}", "command line")
    ov = over if over is not None else (rt.over if rt.over is not None else ("final" if lfre else "window"))
    blk = block or rt.block or ("all" if lfre else "x")
    if blk != "all" and blk not in exp.blocks:
        raise _bad(f"--block: unknown block {blk!r}; expected all or one of {', '.join(exp.blocks)}", "command line")
    return sp, MetricSpec(name, tuple(ov) if isinstance(ov, (list, tuple)) else ov, blk)


def _plain(d: dict[str, Any]) -> dict[str, Any]:
    return {k: (list(v) if isinstance(v, (tuple, frozenset, set)) else v) for k, v in d.items()}
