"""What goes on the wire between the roles: the message schemas of a scenario
(:class:`Wire`), how a message is encoded (:func:`_msg`), whom a done report went to
(:func:`report_to`, :func:`receivers_of`), diagnostics carried as metadata, and the
counters of rejected messages per sender and reason (:class:`Rejects`)."""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from transport.codec import MIN_ID, MONITOR_ID, PLANT_ID, Message, Schema, encode_fields

if TYPE_CHECKING:
    from agents.rounds import PlantTeam, Team

__all__ = ["Wire", "Rejects", "REASONS", "UNKNOWN", "who_name", "diagnostics_meta", "diagnostics_from_meta", "_msg",
           "out_ids_of", "report_to", "receivers_of", "DIAG_PREFIX", "MAX_DIAGNOSTICS"]

UNKNOWN = MIN_ID  # sender code of a message whose key names no sender
REASONS = ("size", "decode", "type", "keys", "version", "sender", "shape", "nonfinite", "key", "range", "neighbour",
           "invalid", "impersonation", "unauthenticated")  # the last two: transport.linkauth


def who_name(sender: int | None) -> str:
    if sender is None or sender == UNKNOWN:
        return "unknown"
    return {PLANT_ID: "plant", MONITOR_ID: "monitor"}.get(sender, str(sender))


class Wire:
    """The schemas of one scenario's messages (``team``: the experiment or a slice of it)."""

    def __init__(self, team: Team) -> None:
        n, N = team.n, team.N
        self.n, self.N = n, N
        self.ny = int(team.ny)
        self.loc = Schema({"meas": {"y": (None,), "wait": (None, 2)}, "ctl": {"wait": (None, 2)}})
        self.truth = Schema({"truth": {"x": (n,)}})
        self.est = Schema({"est": {"x": (None,)}})
        #: a done key carries a report ("done": the estimate, whom the round's messages went
        #: to and their stamps) or, from an agent that broadcast its estimate stamped with the
        #: round to every out-neighbour, the estimate alone ("est": see :func:`report_to`)
        self.done = Schema({"done": {"x": (n,), "to": (None,), "stamps": (None,)}, "est": {"x": (n,)}})
        self.ctl = Schema({"ctl": {}})
        self.stats = Schema({"ctl": {"links": (None, 6), "rejected": (None, 3), "ages": (None, 6), "out": (None, 2)}})


DIAG_PREFIX = "d_"
MAX_DIAGNOSTICS = 12  # the codec carries at most 16 metadata entries


def diagnostics_meta(estimator: Any) -> dict[str, Any]:
    """An estimator's diagnostics and attack flag as done-report metadata
    (``flag``; ``d:NAME`` per finite value; a non-finite value is left out and reads as
    missing, NaN, at the monitor)."""
    from agents.monitor import read_diagnostics

    diag, flag = read_diagnostics(estimator)
    meta: dict[str, Any] = {}
    if flag is not None:
        meta["flag"] = bool(flag)
    for name, v in list((diag or {}).items())[:MAX_DIAGNOSTICS]:
        key = DIAG_PREFIX + name
        if np.isfinite(v) and len(key) <= 32 and key.replace("_", "a").isalnum() and key.isascii():
            meta[key] = float(v)  # names the codec cannot carry are left out
    return meta


def diagnostics_from_meta(meta: Any) -> tuple[dict[str, float], bool | None]:
    diag = {k[len(DIAG_PREFIX):]: float(v) for k, v in meta.items()
            if isinstance(k, str) and k.startswith(DIAG_PREFIX) and isinstance(v, (int, float)) and not isinstance(v, bool)}
    flag = meta.get("flag")
    return diag, (bool(flag) if isinstance(flag, bool) else None)


class Rejects:
    """Bad messages per claimed sender and reason."""

    def __init__(self) -> None:
        self.counts: Counter[tuple[int, str]] = Counter()

    def add(self, sender: int | None, reason: str) -> None:
        self.counts[(UNKNOWN if sender is None else sender, reason if reason in REASONS else "invalid")] += 1

    def as_array(self) -> np.ndarray:
        rows = [(s, REASONS.index(r), c) for (s, r), c in sorted(self.counts.items())]
        return np.array(rows, dtype=float).reshape(-1, 3)

    @staticmethod
    def merge(into: dict[str, dict[str, int]], rows: np.ndarray) -> None:
        for s, r, c in np.asarray(rows).reshape(-1, 3):
            s, r, c = int(s), int(r), int(c)
            if not (0 <= r < len(REASONS)) or c < 0:
                continue
            rec = into.setdefault(who_name(s), {"total": 0})
            rec["total"] += c
            rec[REASONS[r]] = rec.get(REASONS[r], 0) + c

    @staticmethod
    def mine(team: dict[str, dict[str, int]], rows: np.ndarray) -> dict[str, dict[str, int]]:
        """One receiver's rejected messages per sender and reason, merged into the team's too."""
        mine: dict[str, dict[str, int]] = {}
        Rejects.merge(mine, rows)
        Rejects.merge(team, rows)
        return mine


def _msg(kind: str, sender: int, stamp: int, arrays: dict, **kw: Any) -> bytes:
    return encode_fields(kind, sender, stamp, arrays, **kw)


def out_ids_of(exp: PlantTeam) -> dict[int, list[int]]:
    """Agent id -> the ids of its out-neighbours (whom a broadcast report went to)."""
    ids = exp.agent_ids
    return {aid: [ids[j] for j in exp.out_neighbours(i)] for i, aid in enumerate(ids)}


def report_to(m: Message, out_ids: Sequence[int], team: int) -> tuple[list[int], list[int]] | None:
    """Whom the round of a done-key message went to and with which stamps: every one of
    ``out_ids`` (the sender's out-neighbours) stamped with the round for an "est" (a
    broadcast report), else :func:`receivers_of`."""
    if m.kind == "est":
        return broadcast_to(out_ids, m.stamp)
    return receivers_of(m, team)


def broadcast_to(out_ids: Sequence[int], stamp: int) -> tuple[list[int], list[int]]:
    """A broadcast report's receivers (every out-neighbour) and stamps (the round)."""
    return list(out_ids), [stamp] * len(out_ids)


def receivers_of(m: Message, team: int) -> tuple[list[int], list[int]] | None:
    """A done report's receivers and stamps as ints, or None when they do not pair up,
    are more than ``team`` or are not whole numbers in the stamps' range."""
    to, stamps = m.arrays["to"].tolist(), m.arrays["stamps"].tolist()
    if len(stamps) != len(to) or len(to) > team:
        return None
    if to:  # finite (the codec checked): whole numbers in [0, 2**53), in C loops (a report a round per peer)
        values = to + stamps
        if min(values) < 0 or max(values) >= 2**53 or not all(map(float.is_integer, values)):
            return None
    return list(map(int, to)), list(map(int, stamps))
