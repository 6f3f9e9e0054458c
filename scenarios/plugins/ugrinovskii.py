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

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import numpy as np

from estimation import graphs
from estimation.base import Diagnostics, Flags
from estimation.errors import DesignError, NumericalError, ScenarioError
from estimation.hinf_lmi import ResilientProblem, node_riccati_data
from estimation.hinf_riccati import RiccatiFlow
from estimation.ugrinovskii import UgrinovskiiBaseline, UgrinovskiiNode
from estimation.ugrinovskii_example import PAPER_GAMMA2, PAPER_GAMMA2_BAR, example_problem

from ..common import STREAM_AGENT_X0, STREAM_ESTIMATOR, Condition, checked_design, estimator_section, rng_for
from ..helpers import init_vector

if TYPE_CHECKING:
    from estimation.ugrinovskii import _NodeBase as _Node  # what the mixin below is mixed into

    from ..build import Experiment
else:
    _Node = object

from .ugrinovskii_design import UgrinovskiiDesign, _attack_specs
from .ugrinovskii_design import design as _lmi_design
from .ugrinovskii_plants import PLANTS as PLANTS  # the plugin contract's named plants
from .ugrinovskii_plants import AttackSignal, DisturbanceSignal
from .ugrinovskii_schema import Disturbance, UgrinovskiiEstimator

ESTIMATOR = UgrinovskiiEstimator


def _section(exp: "Experiment") -> UgrinovskiiEstimator:
    """This plugin's ``[estimator]`` section of ``exp``, typed."""
    return estimator_section(exp, UgrinovskiiEstimator)


# ============================================================================ estimators
class _Runtime(Diagnostics, Flags, _Node):
    """What the runtime adds to the core nodes: receiver-side channel noise ``H_ij v_ij``
    on ``c_ij`` and ``H_c,ij v_c,ij`` on ``eta_ij`` (for neighbours heard from), the
    attack flag and the diagnostics (``u_i``, and the attacker's ``f``, ``f_c`` for plots)."""

    if TYPE_CHECKING:  # each node class the mixin is mixed into defines it
        @property
        def attack_indicator(self) -> np.ndarray: ...

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

    def _plain_inputs(self) -> bool:
        return self._noise_c is None and self._noise_eta is None

    def _after_step(self) -> None:
        self._flag(self.t, float(np.max(np.abs(self.attack_indicator), initial=0.0)))

    @classmethod
    def _after_steps(cls, members, indicators) -> None:
        """:meth:`_after_step` of every member from the stacked indicators ``(M, nf)``."""
        peak = np.max(np.abs(indicators), axis=1, initial=0.0)
        for m, u in zip(members, peak.tolist()):
            if u > m.threshold or m._above_since is not None:  # else the update leaves the flag down
                m._flag(m.t, u)

    def _flag(self, t: float, peak: float) -> None:
        """The flag's update at time ``t`` from ``max |u_i|`` (``peak``)."""
        above = t >= self.flag_from - 1e-9 * max(1.0, self.flag_from) and peak > self.threshold
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

    @classmethod
    def _diagnostic_rows(cls, members, indicators):
        """Every member's :meth:`diagnostics` (as ``(M,)`` rows) and :attr:`flagged` (``(M,)``
        bool), from the stacked indicators ``(M, nf)``."""
        M = len(members)
        nf = members[0]._nf
        if any(m._nf != nf for m in members):
            return None
        if indicators is None:
            return {}, None  # only asked whether
        t = members[0].t
        f, fc = np.zeros((M, nf)), np.zeros((M, nf))
        for i, m in enumerate(members):
            if m._f_obs is not None:
                f[i] = m._f_obs(t)
            if m._f_det is not None:
                fc[i] = m._f_det(t)
        flags = np.array([m._flagged for m in members])
        if nf == 1:
            return {"u": indicators[:, 0], "f": f[:, 0], "f_c": fc[:, 0]}, flags
        out = {}
        for name, arr in (("u", indicators), ("f", f), ("f_c", fc)):
            out.update({f"{name}{c + 1}": arr[:, c] for c in range(nf)})
        return out, flags

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
    est = _section(exp)
    des: UgrinovskiiDesign = exp.design
    pb = des.problem
    nf = pb.F[i].shape[1]
    specs = _attack_specs(exp)
    sig = {t: (AttackSignal(specs[(i, t)], nf, dt=exp.dt, seed=exp.seed, source=exp.source) if (i, t) in specs else None)
           for t in ("observer", "detector")}
    if not est.controlled:
        sig["detector"] = None  # the baseline has no detector to attack
    x0 = init_vector(est.x0, exp.n, rng_for(exp.seed, STREAM_AGENT_X0, i), where="estimator.x0")

    def noise(spec: Disturbance, which: int, mats: Mapping) -> list | None:
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
    est = _section(exp)
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
        if _section(exp).controlled:
            A_, B_, S = node_riccati_data(pb, "det", {(i, j): d[f"U_{i}_{j}"] for j in nb}, i)
            flows.append((f"detector (35) of node {aid}",
                          RiccatiFlow(A=A_, B=B_, S=S, R=d[f"R_{i}"], gamma2=g, Y0=g * np.linalg.inv(d[f"Q_{i}"]),
                                      dt=exp.dt, name=f"detector Riccati (35) of node {aid}")))
        A_, B_, S = node_riccati_data(pb, "obs", {(i, j): d[f"Ubar_{i}_{j}"] for j in nb}, i)
        flows.append((f"observer (41) of node {aid}",
                      RiccatiFlow(A=A_, B=B_, S=S, R=d[f"Rbar_{i}"], gamma2=gb, Y0=gb * np.linalg.inv(d[f"Qbar_{i}"]),
                                  dt=exp.dt, name=f"observer Riccati (41) of node {aid}")))
    return flows


def design(exp: "Experiment", *, check: bool = True) -> UgrinovskiiDesign | None:
    """The LMI design (:func:`.ugrinovskii_design.design`); for a run (``check``) also one
    step of every node's Riccati equations at ``run.dt``: a step past a solution's escape
    time is refused here, naming the key, rather than met in the run's first round."""
    des = _lmi_design(exp, check=check)
    if check and des is not None:
        try:
            for _, fl in riccati_flows(exp, des):
                fl.step()
        except (NumericalError, DesignError) as exc:
            raise ScenarioError(f"run.dt: {exc} within one step of {exp.dt:g} s; use a shorter step",
                                source=exp.source) from None
    return des


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
            scale = float(np.linalg.norm(fl.Y_stationary))
            for _ in range(exp.n_rounds):
                Y = fl.step()  # raises NumericalError when Y stops being positive definite or bounded
                lam = np.linalg.eigvalsh(Y)
                lo, hi, tr = min(lo, lam[0]), max(hi, lam[-1]), max(tr, float(np.trace(Y)))
                if np.linalg.norm(fl.deviation) <= 1e-13 * scale:
                    break  # at the stationary solution: the rest of the horizon adds nothing (check needs no per-round work)
            out[kind] = [float(lo), float(hi)]
            out["trace_ratio"] = max(out["trace_ratio"], tr / fl.bound)
    except (NumericalError, DesignError) as exc:
        out["ok"], out["error"] = False, str(exc)
    return out


def conditions(exp: "Experiment") -> list[Condition]:
    """gamma^2, gamma_bar^2 (with the paper's values for Section IV), the back-off, and
    the Riccati solutions over the horizon (positive definite and bounded)."""
    est = _section(exp)
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
        "controlled": _section(exp).controlled,
        "source": des.source,
        "gamma2": float(d["gamma2"]), "gamma2_bar": float(d["gamma2_bar"]),
        "nodes": {str(aid): i for i, aid in enumerate(exp.agent_ids)},
        "note": "lmi: the full design (estimation.hinf_lmi.design's dict; node i = agent index i); "
                "usable as estimator.design_cache",
        "lmi": d,
    }
