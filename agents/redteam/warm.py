"""The first trials of a new search: the scenario's own attacks, then their escalation."""

from __future__ import annotations

import math
from typing import Any

from .space import Space

__all__ = ["warm_start"]


def warm_start(sp: Space) -> list[dict[str, Any]]:
    """Optuna parameters of the first trials: the scenario's own attacks (the hand-picked
    one the search must beat), then the same attacks escalated: at the space's largest
    magnitude, copied onto the first other banks / agents up to the budget; with the
    scenario's erasure probability and seed. Parameters that do not fit the space are
    left to the sampler."""
    sens = [(b, a) for a in sp.own if a.target == "sensor" and a.kind != "trajectory" for b in a.sensors]
    byz = [(g, a) for a in sp.own if a.target == "agent" for g in a.agents]
    out = []
    for escalate in (False, True):
        p: dict[str, Any] = {}
        slots = [(b, a) for b, a in sens if b in sp.banks and a.kind in sp.kinds][: sp.sensors]
        if escalate and slots:  # the same waveform on the next banks
            spare = [b for b in sp.banks if b not in {x for x, _ in slots}]
            slots += [(b, slots[0][1]) for b in spare][: sp.sensors - len(slots)]
        for i, (bank, a) in enumerate(slots):
            size = {"constant": a.value, "sine": a.amplitude, "random": a.scale,
                    "ramp": a.slope * max(sp.horizon - a.start, sp.dt)}[a.kind]
            size = math.copysign(sp.amplitude, size or 1.0) if escalate else size
            if abs(size) > sp.amplitude or not sp.start[0] <= a.start <= sp.start[1]:
                continue
            p.update({f"s{i}_kind": a.kind, f"s{i}_bank": bank, f"s{i}_size": float(size), f"s{i}_start": a.start})
            if a.kind == "sine" and sp.omega[0] <= a.omega <= sp.omega[1]:
                p.update({f"s{i}_omega": a.omega, f"s{i}_phase": a.phase % (2 * math.pi)})
        agents = [(g, a) for g, a in byz if g in sp.candidates and a.kind in sp.strategies][: sp.agents]
        if escalate and agents:  # the same strategy from the next agents
            spare = [g for g in sp.candidates if g not in {x for x, _ in agents}]
            agents += [(g, agents[0][1]) for g in spare][: sp.agents - len(agents)]
        for i, (agent, a) in enumerate(agents):
            if not sp.start[0] <= a.start <= sp.start[1]:
                continue
            p.update({f"a{i}_agent": agent, f"a{i}_kind": a.kind, f"a{i}_start": a.start})
            if a.kind == "constant" and abs(a.value) <= sp.value:
                p[f"a{i}_value"] = math.copysign(sp.value, a.value or 1.0) if escalate else a.value
            elif a.kind in ("huge", "equivocation") and min(1e-3, sp.value) <= a.scale <= sp.value:
                p[f"a{i}_scale"] = sp.value if escalate else a.scale
        if sp.drop_p > 0:
            p["drop_p"] = min(sp.p, sp.drop_p)
            if sp.seed:
                p["seed"] = sp.base_seed
        if p and p not in out:
            out.append(p)
    return out
