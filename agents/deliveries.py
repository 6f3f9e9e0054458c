"""The delivery record of a run (DESIGN.md, "Deliveries are data"): what each agent held
when it stepped, written as the run goes, and read back for ``rse replay``.

Every agent process appends, per agent and per round it ran, the round ``k``, the
measurement it used (or none) and, per in-neighbour, the round stamp of the message in
its inbox (or -1: none yet); a Byzantine agent also appends what its strategy addressed
to each receiver (receiver, stamp, payload). Each agent incarnation (a process start: a
killed and restarted agent is a second one) writes its own file,
``deliveries/agent-IIII-NNN.rec``: a header block, then one block per round, each block
``uint32 length`` + a msgpack map whose values are little-endian column buffers, written
with one ``write`` to an unbuffered file. A writer killed at any moment (SIGKILL included)
leaves every block it completed readable; :func:`read_record` stops at a torn last block.

Imported by agent processes: numpy and msgpack only (no pyarrow, no scenario schema).
"""

from __future__ import annotations

import os
import struct
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgpack
import numpy as np

from estimation.errors import ScenarioError

from .rounds import addressed

DIR = "deliveries"
VERSION = 1
_LEN = struct.Struct("<I")
#: a block larger than this is not one a writer wrote (a corrupt or foreign file)
MAX_BLOCK = 1 << 26


class DeliveryWriter:
    """The record of one agent incarnation (the ``tap`` of its :class:`~agents.node.AgentNode`:
    :meth:`stepped` before each estimator step, :meth:`sent` after a Byzantine publication)."""

    def __init__(self, run_dir: str | Path, agent_id: int, in_ids: Iterable[int], index_of: dict[int, int]) -> None:
        d = Path(run_dir) / DIR
        d.mkdir(parents=True, exist_ok=True)
        self.in_ids = [int(j) for j in in_ids]
        self._idx = [index_of[j] for j in self.in_ids]
        n = 0
        while True:  # O_EXCL: a restarted agent never appends to an earlier incarnation's file
            self.path = d / f"agent-{agent_id:04d}-{n:03d}.rec"
            try:
                self._fd: int | None = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_APPEND, 0o644)
                break
            except FileExistsError:
                n += 1
        self.bytes = 0
        self._write({"v": VERSION, "agent": int(agent_id), "in": self.in_ids})

    def _write(self, block: dict[str, Any]) -> None:
        if self._fd is None:
            return
        body = msgpack.packb(block)
        self.bytes += os.write(self._fd, _LEN.pack(len(body)) + body)

    def stepped(self, k: int, y: np.ndarray | None, inbox: dict[int, Any]) -> None:
        """Round ``k``: measurement ``y`` (None: none) and the inbox (index -> Received)."""
        stamps = np.array([r.stamp if (r := inbox.get(ix)) is not None else -1 for ix in self._idx], dtype="<i8")
        self._write({"k": int(k), "y": None if y is None else np.ascontiguousarray(y, dtype="<f8").tobytes(),
                     "s": stamps.tobytes()})

    def sent(self, k: int, msg: Any, receivers: Iterable[int]) -> None:
        """A Byzantine agent's round-``k`` publication (an addressed mapping or a broadcast)."""
        rows = addressed(msg, k, receivers) if isinstance(msg, dict) else [(j, k, msg) for j in receivers]
        if not rows:
            return
        x = np.stack([np.asarray(v, dtype="<f8").reshape(-1) for _, _, v in rows])
        self._write({"k": int(k), "to": np.array([r[0] for r in rows], dtype="<i8").tobytes(),
                     "st": np.array([r[1] for r in rows], dtype="<i8").tobytes(), "x": x.tobytes(), "w": x.shape[1]})

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None


def attach(nodes: Iterable[Any], run_dir: str | Path) -> list[DeliveryWriter]:
    """Record what each of ``nodes`` (:class:`~agents.node.AgentNode`) steps on into
    ``run_dir``; returns the writers (close them when the process ends)."""
    writers = []
    for node in nodes:
        w = DeliveryWriter(run_dir, node.id, list(node.links), node.index_of)
        node.tap = w
        writers.append(w)
    return writers


# ------------------------------------------------------------------ reading


@dataclass
class Incarnation:
    """One agent process's record, as columns: ``k`` (R,), ``y`` (list of arrays or
    None), ``stamps`` (R, in-neighbours; -1: none), the sends of a Byzantine agent as
    ``(k, receiver, stamp, payload)``."""

    agent: int
    in_ids: list[int]
    k: np.ndarray
    y: list[np.ndarray | None]
    stamps: np.ndarray
    sends: list[tuple[int, int, int, np.ndarray]] = field(default_factory=list)
    torn: bool = False  # the last block was cut short (a killed writer)


def _blocks(data: bytes) -> tuple[list[dict[str, Any]], bool]:
    out: list[dict[str, Any]] = []
    pos = 0
    while pos + 4 <= len(data):
        (n,) = _LEN.unpack_from(data, pos)
        if n > MAX_BLOCK or pos + 4 + n > len(data):
            return out, True
        try:
            out.append(msgpack.unpackb(data[pos + 4: pos + 4 + n]))
        except (ValueError, msgpack.UnpackException):
            return out, True
        pos += 4 + n
    return out, pos != len(data)


def read_incarnation(path: Path) -> Incarnation | None:
    """One record file (None: not even its header was written)."""
    blocks, torn = _blocks(path.read_bytes())
    if not blocks or not isinstance(blocks[0], dict) or blocks[0].get("v") != VERSION:
        if blocks:
            raise ScenarioError(f"{path}: not a delivery record of this version (expected v={VERSION})")
        return None
    head = blocks[0]
    in_ids = [int(j) for j in head["in"]]
    ks, ys, st, sends = [], [], [], []
    try:
        for b in blocks[1:]:
            if "to" in b:
                x = np.frombuffer(b["x"], dtype="<f8").reshape(-1, int(b["w"]))
                for to, s, v in zip(np.frombuffer(b["to"], "<i8"), np.frombuffer(b["st"], "<i8"), x):
                    sends.append((int(b["k"]), int(to), int(s), v))
                continue
            ks.append(int(b["k"]))
            ys.append(None if b["y"] is None else np.frombuffer(b["y"], dtype="<f8"))
            st.append(np.frombuffer(b["s"], dtype="<i8"))
        stamps = np.array(st, dtype=np.int64).reshape(len(ks), len(in_ids))
    except (KeyError, TypeError, ValueError) as exc:
        raise ScenarioError(f"{path}: a malformed block ({exc})") from None
    return Incarnation(int(head["agent"]), in_ids, np.array(ks, dtype=np.int64), ys, stamps, sends, torn)


def record_files(run_dir: str | Path) -> list[Path]:
    """The record's files (a :class:`~estimation.errors.ScenarioError` when there are none)."""
    d = Path(run_dir) / DIR
    paths = sorted(d.glob("agent-*.rec")) if d.is_dir() else []
    if not paths:
        raise ScenarioError(f"{run_dir}: no delivery record ({DIR}/ is missing or empty; was it written by `rse run`?)")
    return paths


def read_record(run_dir: str | Path) -> dict[int, list[Incarnation]]:
    """Agent id -> its incarnations in the order they started (``RUN_DIR/deliveries``);
    a missing or malformed record is a :class:`~estimation.errors.ScenarioError` (bad input)."""
    out: dict[int, list[Incarnation]] = {}
    for p in record_files(run_dir):
        inc = read_incarnation(p)
        if inc is not None:
            out.setdefault(inc.agent, []).append(inc)
    return out


def record_bytes(run_dir: str | Path) -> tuple[int, int]:
    """``(bytes, agent-rounds)`` of a run's record."""
    d = Path(run_dir) / DIR
    total = sum(p.stat().st_size for p in d.glob("agent-*.rec"))
    rounds = sum(len(inc.k) for incs in read_record(run_dir).values() for inc in incs)
    return total, rounds
