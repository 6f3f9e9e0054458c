"""Plugin: Mitra, Richards, Bagchi, Sundaram (2019), mobile agents, LFRE and SW-LFRE;
with the named plants ``cells`` and ``diffusion`` of its Section 8."""

from __future__ import annotations

from typing import TYPE_CHECKING, Literal

import numpy as np
from pydantic import Field

from estimation import cells as cell_models
from estimation import lfre
from estimation.errors import DesignError, ScenarioError
from estimation.lti import ContinuousLTI, stacked_banks
from estimation.mss import effective_erasure_probability, max_erasure_probability, mss_margin, robustness_multiplier
from estimation.patrols import Patrol
from estimation.robustness import strong_robustness

from ..common import STREAM_MAP, Condition, PlantModel, ThreatModel, checked_design, estimator_section, rng_for
from ..helpers import check_size, plant_params
from ..types import Strict

if TYPE_CHECKING:
    from ..build import Experiment
    from ..schema import Scenario


class MitraEstimator(Strict):
    """Mitra et al. 2019: switched partial observers (7)-(8) and resilient fusion."""

    algorithm: Literal["lfre"]
    #: lfre: (21)-(22); sw_lfre: (14) with time stamps; median: Remark 7; average: non-resilient
    rule: Literal["lfre", "sw_lfre", "median", "average"] = "lfre"
    f: int = Field(default=1, ge=0)
    #: MEDAG in-degree (default 2f + 1)
    r: int | None = Field(default=None, ge=1)
    #: sampled-error pole target for the switched observers
    target: float = Field(default=0.5, ge=0, lt=1)
    deadbeat: bool = False
    fuse_stable: bool = True


ESTIMATOR = MitraEstimator
THREAT_MODEL = ThreatModel(agents="f")  # Theorem 2: f-local Byzantine agents, erasures up to drop_p


def _section(exp: "Experiment") -> MitraEstimator:
    """This plugin's ``[estimator]`` section of ``exp``, typed."""
    return estimator_section(exp, MitraEstimator)


def _cell_plant(sc: "Scenario", source: str, defaults: dict) -> PlantModel:
    pl = sc.plant
    if pl.A is not None or pl.B is not None:
        raise ScenarioError(f"plant: A and B are given by model {pl.model!r}", source=source)
    if pl.time == "continuous":
        raise ScenarioError(f"plant.time: model {pl.model!r} is a discrete-time plant", source=source)
    if sc.sensors is not None:
        raise ScenarioError(f"sensors: the sensing locations are given by model {pl.model!r}", source=source)
    p = plant_params(pl, defaults, source, integers={key: (1, None) for key in ("K", "states", "locations")})
    per_cell = "states" if pl.model == "cells" else "locations"
    check_size("states", p["K"] * p[per_cell], f"plant.params.K x plant.params.{per_cell}", run=sc.run, source=source)
    rng = rng_for(sc.run.seed, STREAM_MAP)
    try:
        if pl.model == "cells":
            m = cell_models.cells(p["K"], rng, cell_size=p["cell_size"], states=p["states"],
                                  lam_range=(p["lam_low"], p["lam_high"]))
        else:
            m = cell_models.diffusion(p["K"], rng, eps=p["eps"], radius=p["radius"], cell_size=p["cell_size"],
                                      locations=p["locations"])
    except DesignError as exc:
        raise ScenarioError(f"plant: {exc}", source=source) from None
    n = m.A.shape[0]
    # every location's rows as views of one stacked C (the plant's C is that array, no copy)
    banks = stacked_banks([np.atleast_2d(c) for c in m.loc_C])
    lti = ContinuousLTI(A=m.A, B=np.zeros((n, 0)), banks=banks, state_names=tuple(f"x{i + 1}" for i in range(n)))
    blocks = {name: np.flatnonzero(m.state_block == b) for b, name in enumerate(m.block_names)}
    return PlantModel(lti=lti, discrete=True, positions=np.asarray(m.positions), x0=np.asarray(m.x0),
                      blocks=blocks, cell_of_location=np.asarray(m.loc_cell))


_CELLS = {"K": 4, "states": 20, "lam_low": 0.5, "lam_high": 1.2, "cell_size": 30.0}
_DIFFUSION = {"K": 4, "locations": 10, "eps": 0.01, "radius": 15.0, "cell_size": 30.0}
PLANTS = {
    "cells": (_CELLS, lambda sc, source: _cell_plant(sc, source, _CELLS)),
    "diffusion": (_DIFFUSION, lambda sc, source: _cell_plant(sc, source, _DIFFUSION)),
}


def _static_patrol(exp: "Experiment", i: int) -> Patrol:
    rows = exp.agent_rows[i]
    banks = [b for b, r in enumerate(exp.bank_rows) if len(r) == len(rows) and np.array_equal(r, rows)]
    if len(banks) != 1:
        raise ScenarioError(f"agents: agent {exp.agent_ids[i]} reads several banks; an lfre agent reads one location per round", source=exp.source)
    return Patrol((banks[0],), (0,), (1,), agent=exp.agent_ids[i])


def design(exp: "Experiment", *, check: bool = True) -> "lfre.MitraDesign | None":
    est = _section(exp)
    if not exp.discrete:
        raise ScenarioError("estimator.algorithm: 'lfre' is a discrete-time estimator; set plant.time = 'discrete'", source=exp.source)
    patrols = [pt if pt is not None else _static_patrol(exp, i) for i, pt in enumerate(exp.patrols)]
    names = [b for b in exp.blocks if b != "x"]
    try:
        return lfre.design(exp.plant.A, exp.plant.banks, patrols, exp.Adj, f=est.f, r=est.r, target=est.target,
                           deadbeat=est.deadbeat, fuse_stable=est.fuse_stable,
                           blocks=[exp.blocks[b] for b in names] or None, block_names=names or None)
    except DesignError as exc:
        if not check:
            return None
        raise ScenarioError(f"estimator: {exc}", source=exp.source) from None


def make_estimator(exp: "Experiment", i: int):
    return lfre.make_estimator(exp.design, agent=i, rule=_section(exp).rule)


def conditions(exp: "Experiment") -> list[Condition]:
    """Source sets, strong robustness, MEDAG levels per block, and Theorem 2's MSS test."""
    est = _section(exp)
    des, out = checked_design(exp, design, "MEDAG for every mode (Definition 2, Lemma 2)")
    if des is None:
        return out
    ids = exp.agent_ids
    names = [b for b in exp.blocks if b != "x"] or ["x"]
    r_min = np.inf
    for b, name in enumerate(names):
        modes = [j for j in des.medags if names == ["x"] or int(des.modal.block_of_mode[j]) == b]
        if not modes:
            continue
        S = sorted(des.sources[modes[0]])
        rob = min(strong_robustness(des.Adj, des.sources[j]) for j in modes)
        r_min = min(r_min, rob)
        levels = des.medags[modes[0]].levels
        lv = " | ".join("{" + ",".join(str(ids[i]) for i in level) + "}" for level in levels)
        out.append(Condition(f"{name}: source set S_j", None, "agents " + ",".join(str(ids[i]) for i in S)))
        out.append(Condition(f"{name}: strongly (2f+1) = {2 * est.f + 1}-robust w.r.t. S_j", rob >= 2 * est.f + 1,
                             f"strong robustness {rob}"))
        out.append(Condition(f"{name}: MEDAG levels", None, lv))
    rho = float(np.max(np.abs(des.modal.lam)))
    m = robustness_multiplier(r_min, f=est.f) if est.f > 0 else np.inf
    out.append(Condition("strongly (mf+1)-robust: m", None, f"m = {m} (min strong robustness {r_min}, f = {est.f})"))
    p = exp.scenario.network.channel.drop_p
    if np.isfinite(m) and m >= 1 and est.f > 0:
        pbar = effective_erasure_probability(p, m=int(m), f=est.f)
        margin = mss_margin(p, rho=rho, m=int(m), f=est.f)
        pmax = max_erasure_probability(rho=rho, m=int(m), f=est.f)
        out.append(Condition(f"MSS (Theorem 2): rho^2 pbar < 1 at p = {p:g}", bool(margin < 1),
                             f"rho = {rho:.6g}, pbar = {pbar:.6g}, rho^2 pbar = {margin:.6g}"))
        out.append(Condition("largest tolerable erasure probability p (eqs. 23-24)", None, f"{pmax:.6g}"))
    return out


def design_json(exp: "Experiment") -> dict:
    d = exp.design
    if d is None:
        return {}
    return {
        "f": d.f, "r": d.r, "eigenvalues": d.modal.lam,
        "sources": {int(j): sorted(exp.agent_ids[i] for i in s) for j, s in enumerate(d.sources)},
        "medag_levels": {int(j): [[exp.agent_ids[i] for i in lv] for lv in m.levels] for j, m in d.medags.items()},
    }
