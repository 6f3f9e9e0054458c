"""The ``grid`` plant model: a pandapower network (IEEE 14-, 30-, 118-bus ... or a file saved
from pandapower) as the Kron-reduced swing dynamics of its generators (:mod:`estimation.grid`),
with PMUs at generator buses. pandapower (the ``grid`` extra) is imported only here, only
when a scenario uses the model.

Bus numbers in scenario files are 1-based: pandapower's bus index + 1 (the IEEE numbers of
the built-in cases).
"""

from __future__ import annotations

import logging
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from estimation.errors import DesignError, ScenarioError
from estimation.grid import SwingModel, damping, inertia, susceptance_matrix, swing_model
from estimation.lti import ContinuousLTI, zoh

from ..common import PlantModel

if TYPE_CHECKING:
    from ..schema import Scenario

#: documented defaults: inertia constant H (s, on the machine rating; Kundur 1994, Table 3.2,
#: thermal units 2.5-10 s) and damping d (p.u. power per p.u. frequency; Kundur 1994,
#: Sec. 11.1.3, load damping 1-2); areas: PMU banks as that many groups of generator buses;
#: frequency = 0: the PMUs' angle rows only (a single-output observer per PMU)
_GRID = {"H": 5.0, "D": 2.0, "areas": 0.0, "frequency": 1.0}
EXTRA = "pip install 'resilient-state-estimation[grid]'"
# matpower column numbers (pandapower's internal ppc arrays)
BUS_PD, BUS_GS, F_BUS, T_BUS, BR_X, TAP, SHIFT, GEN_PG = 2, 4, 0, 1, 3, 8, 9, 1


@dataclass(frozen=True)
class DCNetwork:
    """A network's DC data (p.u. on ``base_mva``), positions = pandapower's internal order.

    ``pd_bus[i]``: pandapower's bus index of position ``i``; ``p``: the bus injections of the
    operating point (generation minus load, minus the phase shifters' and shunts' constant
    terms, so that ``B theta = p`` holds for pandapower's DC power flow angles ``theta``).
    """

    pd_bus: np.ndarray
    f: np.ndarray
    t: np.ndarray
    b: np.ndarray
    p: np.ndarray
    base_mva: float
    f_hz: float
    theta: np.ndarray  # pandapower's DC power-flow angles (rad), per position


@contextmanager
def _quiet() -> Iterator[None]:
    """pandapower's warnings and log lines (e.g. 'numba cannot be imported') silenced."""
    log = logging.getLogger("pandapower")
    level = log.level
    log.setLevel(logging.ERROR)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            yield
    finally:
        log.setLevel(level)


def _require_pandapower(source: str) -> None:
    try:
        with _quiet():
            import pandapower.networks  # noqa: F401
    except ImportError:
        raise ScenarioError(f"plant.model: 'grid' needs pandapower, which is not installed; {EXTRA}", source=source) from None


def pandapower_net(case: str, *, source: str = "<scenario>") -> Any:
    """The pandapower network named ``case`` (``pandapower.networks.<case>()``) or saved in
    the JSON file ``case`` (relative to the scenario file's folder)."""
    _require_pandapower(source)
    import pandapower
    import pandapower.networks as networks

    if case.endswith(".json"):
        path = Path(case)
        if not path.is_absolute() and Path(source).parent.is_dir():
            path = Path(source).parent / path
        if not path.is_file():
            raise ScenarioError(f"plant.case: no pandapower network file {str(path)!r}", source=source)
        try:
            with _quiet():
                return pandapower.from_json(str(path))
        except Exception as exc:  # whatever the file holds, said in one line
            raise ScenarioError(f"plant.case: {str(path)!r} is not a pandapower network: {type(exc).__name__}: {exc}",
                                source=source) from None
    make = getattr(networks, case, None) if case.isidentifier() and not case.startswith("_") else None
    if not callable(make):
        raise ScenarioError(f"plant.case: pandapower has no network {case!r}; expected e.g. 'case14', 'case30', "
                            "'case118' (pandapower.networks) or a .json file saved with pandapower.to_json", source=source)
    with _quiet():
        return make()


def dc_network(net: Any, *, source: str = "<scenario>") -> DCNetwork:
    """Run pandapower's DC power flow (``rundcpp``) once and read the in-service network."""
    import pandapower

    try:
        with _quiet():
            pandapower.rundcpp(net, numba=False)
    except Exception as exc:
        raise ScenarioError(f"plant.case: pandapower's DC power flow fails on this network: {type(exc).__name__}: {exc}",
                            source=source) from None
    ppc = net._ppc["internal"]
    bus, br, gen, base = ppc["bus"].real, ppc["branch"], ppc["gen"].real, float(ppc["baseMVA"])
    lookup = np.asarray(net._pd2ppc_lookups["bus"])
    ppc_pos = {int(v): i for i, v in enumerate(bus[:, 0])}
    pd_bus = np.full(len(bus), -1)
    for pd_i in net.bus.index[net.bus.in_service.to_numpy(bool)]:
        pos = ppc_pos.get(int(lookup[pd_i]))
        if pos is not None and pd_bus[pos] < 0:
            pd_bus[pos] = int(pd_i)
    f, t = br[:, F_BUS].real.astype(int), br[:, T_BUS].real.astype(int)
    f, t = np.array([ppc_pos[v] for v in f]), np.array([ppc_pos[v] for v in t])
    tap = br[:, TAP].real.copy()
    tap[tap == 0] = 1.0
    b = 1.0 / (br[:, BR_X].real * tap)
    shift = np.deg2rad(br[:, SHIFT].real)
    p = -bus[:, BUS_PD] / base - bus[:, BUS_GS] / base
    np.add.at(p, np.array([ppc_pos[int(v)] for v in gen[:, 0]], dtype=int), gen[:, GEN_PG] / base)
    np.add.at(p, f, b * shift)  # matpower makeBdc: Pbusinj = Cft' (b .* -shift), moved to the right
    np.add.at(p, t, -b * shift)
    theta = np.deg2rad(net.res_bus.va_degree.to_numpy(float)[pd_bus])
    return DCNetwork(pd_bus=pd_bus, f=f, t=t, b=b, p=p, base_mva=base, f_hz=float(net.f_hz), theta=theta)


def _machines(net: Any, dc: DCNetwork, p: dict[str, float]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Generator buses (positions, increasing) and their summed ``M``, ``D``: every in-service
    ``gen`` and ``ext_grid``; rating ``sn_mva``, else ``max_p_mw``, else the system base."""
    pos_of = {int(pd): i for i, pd in enumerate(dc.pd_bus)}
    rows = []
    for table in (net.ext_grid, net.gen):
        for _, g in table[table.in_service.astype(bool)].iterrows():
            S = next((float(g[c]) for c in ("sn_mva", "max_p_mw") if c in g and np.isfinite(g[c]) and g[c] > 0), dc.base_mva)
            H = float(g["h_s"]) if "h_s" in g and np.isfinite(g["h_s"]) else p["H"]
            d = float(g["d_pu"]) if "d_pu" in g and np.isfinite(g["d_pu"]) else p["D"]
            rows.append((pos_of[int(g["bus"])], S, H, d))
    buses = np.array(sorted({r[0] for r in rows}), dtype=int)
    M, D = np.zeros(buses.size), np.zeros(buses.size)
    for pos, S, H, d in rows:
        k = int(np.searchsorted(buses, pos))
        M[k] += inertia(H, S, base_mva=dc.base_mva, f_hz=dc.f_hz)
        D[k] += damping(d, S, base_mva=dc.base_mva, f_hz=dc.f_hz)
    return buses, M, D


def grid_model(net: Any, *, H: float = _GRID["H"], D: float = _GRID["D"], source: str = "<scenario>") -> tuple[SwingModel, DCNetwork]:
    """The swing model of a pandapower network and its DC data (inputs: load changes at every
    bus that has an in-service load)."""
    dc = dc_network(net, source=source)
    gen_bus, M, Dg = _machines(net, dc, {"H": H, "D": D})
    pos_of = {int(pd): i for i, pd in enumerate(dc.pd_bus)}
    loads = net.load[net.load.in_service.astype(bool)]
    input_bus = np.array(sorted({pos_of[int(b)] for b in loads.bus if int(b) in pos_of}), dtype=int)
    try:
        B = susceptance_matrix(dc.pd_bus.size, dc.f, dc.t, dc.b)
        return swing_model(B, gen_bus, M=M, D=Dg, input_bus=input_bus), dc
    except DesignError as exc:
        raise ScenarioError(f"plant.case: {exc}", source=source) from None


def _model(case: str, H: float, D: float, source: str) -> tuple[SwingModel, DCNetwork]:
    """:func:`grid_model` of ``case``; a built-in network's is built once per process."""
    if case.endswith(".json"):
        return grid_model(pandapower_net(case, source=source), H=H, D=D, source=source)
    _require_pandapower(source)
    try:
        return _builtin_model(case, H, D)
    except ScenarioError as exc:
        raise ScenarioError(exc.detail, source=source) from None


@cache
def _builtin_model(case: str, H: float, D: float) -> tuple[SwingModel, DCNetwork]:
    return grid_model(pandapower_net(case), H=H, D=D)


def _banks(sc: "Scenario", model: SwingModel, dc: DCNetwork, areas: int, source: str) -> tuple[list[list[int]], list[str]]:
    """PMU banks as lists of generator-bus positions, with their names."""
    gens = [int(g) for g in model.gen_bus]
    number = {g: int(dc.pd_bus[g]) + 1 for g in gens}
    pmus = sc.plant.pmus
    if pmus is None:
        if areas:
            if areas > len(gens):
                raise ScenarioError(f"plant.params.areas: {areas} areas for {len(gens)} generator buses", source=source)
            groups = [list(a) for a in np.array_split(np.array(gens), areas)]
            return groups, [f"area{k + 1}" for k in range(areas)]
        return [[g] for g in gens], [f"pmu{number[g]}" for g in gens]
    if areas:
        raise ScenarioError("plant.params.areas: give areas or plant.pmus, not both", source=source)
    pos_of = {number[g]: g for g in gens}
    banks = []
    for k, entry in enumerate(pmus):
        buses = [entry] if isinstance(entry, int) else list(entry)
        bad = [b for b in buses if b not in pos_of]
        if bad or not buses:
            raise ScenarioError(f"plant.pmus[{k}]: bus(es) {bad or buses} carry no generator; a PMU reads a generator "
                                f"bus, one of {sorted(pos_of)}", source=source)
        banks.append([pos_of[b] for b in buses])
    return banks, ["pmu" + "+".join(str(number[g]) for g in bank) for bank in banks]


def _grid_plant(sc: "Scenario", source: str) -> PlantModel:
    pl = sc.plant
    unknown = set(pl.params) - set(_GRID)
    if unknown:
        raise ScenarioError(f"plant.params: unknown parameter(s) {sorted(unknown)}; expected some of {sorted(_GRID)}", source=source)
    if pl.A is not None or pl.B is not None:
        raise ScenarioError("plant: A and B are given by model 'grid'", source=source)
    if sc.sensors is not None:
        raise ScenarioError("sensors: the sensors of model 'grid' are PMUs (plant.pmus)", source=source)
    if pl.case is None:
        raise ScenarioError("plant.case: model 'grid' needs a network, e.g. case = 'case14'", source=source)
    p = {**_GRID, **pl.params}
    if not p["H"] > 0 or not p["D"] >= 0:
        raise ScenarioError(f"plant.params: expected H > 0 (s) and D >= 0 (p.u.), got H = {p['H']}, D = {p['D']}", source=source)
    if p["frequency"] not in (0.0, 1.0):
        raise ScenarioError(f"plant.params.frequency: expected 1 (angle and frequency rows) or 0 (angle rows only), "
                            f"got {p['frequency']}", source=source)
    if p["areas"] != int(p["areas"]) or p["areas"] < 0:
        raise ScenarioError(f"plant.params.areas: expected a whole number >= 0, got {p['areas']}", source=source)
    model, dc = _model(pl.case, p["H"], p["D"], source)
    groups, names = _banks(sc, model, dc, int(p["areas"]), source)
    rows = 2 if p["frequency"] else 1
    banks = tuple(np.vstack([model.pmu_rows(g)[r:r + 1] for r in range(rows) for g in grp]) for grp in groups)
    G = model.G
    if pl.state_names and len(pl.state_names) != 2 * G:
        raise ScenarioError(f"plant.state_names: expected {2 * G} names, got {len(pl.state_names)}", source=source)
    nums = [int(dc.pd_bus[g]) + 1 for g in model.gen_bus]
    states = tuple(pl.state_names) if pl.state_names else tuple([f"delta{b}" for b in nums] + [f"omega{b}" for b in nums])
    A, B = model.A, model.B
    if pl.time == "discrete":
        A, B = zoh(A, B, sc.run.dt)
    lti = ContinuousLTI(A=A, B=B, banks=banks, state_names=states)
    return PlantModel(lti=lti, discrete=pl.time == "discrete",
                      info={"grid": model, "bank_names": names, "case": pl.case})


PLANTS = {"grid": (_GRID, _grid_plant)}
