"""Equivocation evidence over Zenoh (``rse run --sign DIR``): the simulator's watch
(:mod:`agents.evidence`) carried by the team's processes.

1. **Sign once, at the sender.** Every agent signs each estimate it sends (Ed25519 over run,
   kind ``est``, sender, receiver or -1, stamp and payload; :mod:`transport.signing`): a
   broadcast once per round, an addressed message once per receiver. The signature travels
   in the message's metadata (``sig``, hex).
2. **Receivers tell what they were told.** Each regular agent keeps the signed copies it
   received and, as it publishes round ``k``, sends them on ``ctl/told/{i}`` stamped ``k``
   (sender, receiver field, stamp, values, signature per copy): the copies of stamp
   ``k - 1``, which round ``k`` used, and whatever came since its last report.
3. **Compare digests, verify on conflict.** The monitor keeps, per sender and stamp, the
   BLAKE2b digest of every regular receiver's copy. Equal digests: nothing is verified.
   Two different digests: both signatures are checked against the sender's public key;
   if both hold, the sender is **convicted at the later of the two reports' rounds**, and
   the record (both signed messages) goes to ``RUN_DIR/evidence.jsonl``, the format of
   :func:`agents.evidence.verify_record` (``rse verify-evidence``). A copy whose signature
   fails is counted (``bad_signatures``), never used.

So the cost is one signature per sent message, one report per regular agent and round, one
digest per copy at the monitor, and two verifications per conflict. A regular agent sends one
value per round to everyone: its copies never differ, it cannot be convicted.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from estimation.errors import ScenarioError
from transport.codec import Message, Schema
from transport.signing import digest, payload_bytes, verify

from .wire import _msg

__all__ = ["Signing", "Convictions", "TOLD", "signing_for", "convictions_for", "unsigned"]

TOLD = "told"
KIND = "est"
SIG_WORDS = 16  # a 64-byte signature as 16 uint32 words (exact in float64)
MAX_COPIES = 4096  # what one report may carry (a bound on untrusted input)
KEEP_ROUNDS = 64  # stamps the monitor compares before it forgets them


def unsigned(receiver: int | None, stamp: int, x: Any) -> None:
    """The metadata of an unsigned estimate: none (:meth:`Signing.meta` when signing)."""
    return None


def _words(sig: bytes) -> np.ndarray:
    return np.frombuffer(sig, dtype="<u4").astype(float)


def _sig_bytes(words: np.ndarray) -> bytes | None:
    w = np.asarray(words)
    if w.shape != (SIG_WORDS,) or not np.all((w >= 0) & (w < 2**32) & (w == np.floor(w))):
        return None
    return w.astype("<u4").tobytes()


class Signing:
    """One agent's signing key (None: it signs nothing) and, for a regular agent, the
    copies it reports."""

    def __init__(self, run_id: str, agent_id: int, signer: Any = None, *, regular: bool = False) -> None:
        self.run_id, self.id, self.signer, self.regular = run_id, agent_id, signer, regular and signer is not None
        self.copies: list[tuple[int, int, int, np.ndarray, bytes]] = []  # (from, field, stamp, x, sig)
        self.signatures = 0

    def begin(self, bus: Any, keys: Any, k: int) -> Any:
        """Round ``k``: send the report of what this agent was told, then return how its
        estimates are signed (:meth:`meta`, or :func:`unsigned`)."""
        if self.signer is None:
            return unsigned
        self.report(bus, keys, k)
        return self.meta

    def meta(self, receiver: int | None, stamp: int, x: Any) -> dict[str, Any]:
        """The metadata of a signed estimate: ``{"sig": hex}``."""
        self.signatures += 1
        return {"sig": self.signer.sign(self.run_id, KIND, self.id, receiver, stamp, payload_bytes(x)).hex()}

    def note(self, j: int, m: Message | None) -> None:
        """A regular agent took ``m`` from in-neighbour ``j``: keep its signed copy."""
        if m is None or not self.regular:
            return
        sig = (m.meta or {}).get("sig")
        if (not self.regular or not isinstance(sig, str) or len(sig) != 128 or len(self.copies) >= MAX_COPIES
                or m.arrays["x"].ndim != 1):  # the estimates of every scenario are vectors
            return
        try:
            raw = bytes.fromhex(sig)
        except ValueError:
            return
        self.copies.append((j, -1 if m.receiver is None else int(m.receiver), m.stamp, m.arrays["x"], raw))

    def report(self, bus: Any, keys: Any, k: int) -> None:
        """Send what this agent was told since its last report, stamped ``k``."""
        if not self.copies:
            return
        c, self.copies = self.copies, []
        arrays = {"from": np.array([r[0] for r in c], dtype=float), "field": np.array([r[1] for r in c], dtype=float),
                  "stamps": np.array([r[2] for r in c], dtype=float), "x": np.stack([r[3] for r in c]),
                  "sig": np.stack([_words(r[4]) for r in c])}
        bus.publish(keys.ctl(TOLD, self.id), _msg("ctl", self.id, k, arrays))


class Convictions:
    """The monitor's comparison of the regular agents' reports (see the module docstring)."""

    def __init__(self, run_id: str, public_keys: dict[str, Any], regular: set[int]) -> None:
        self.run_id, self.keys, self.regular = run_id, public_keys, regular
        self.schema = Schema({"ctl": {"from": (None,), "field": (None,), "stamps": (None,), "x": (None, None),
                                      "sig": (None, SIG_WORDS)}})
        self.told: dict[tuple[int, int], dict[int, tuple[int | None, bytes, bytes, bytes, int]]] = {}
        self.convicted: dict[int, int] = {}
        self.records: list[dict[str, Any]] = []
        self.bad_signatures = self.verifications = self.copies = 0
        self.newest = -1

    def add(self, r: int, m: Message) -> None:
        """Receiver ``r``'s report ``m`` (stamped with the round it was sent in)."""
        if r not in self.regular:
            return
        a = m.arrays
        for j, field, stamp, x, words in zip(a["from"], a["field"], a["stamps"], a["x"], a["sig"]):
            sig = _sig_bytes(words)
            if sig is None or not (0 <= stamp <= m.stamp + 1):
                self.bad_signatures += 1
                continue
            self._copy(int(j), None if field < 0 else int(field), int(stamp), r, payload_bytes(x), sig, m.stamp)
        if m.stamp > self.newest:
            self.newest = m.stamp
            for key in [key for key in self.told if key[1] < m.stamp - KEEP_ROUNDS]:
                del self.told[key]

    def _copy(self, j: int, field: int | None, stamp: int, r: int, payload: bytes, sig: bytes, k: int) -> None:
        self.copies += 1
        told = self.told.setdefault((j, stamp), {})
        if r in told:
            return
        d = digest(payload)
        told[r] = (field, payload, sig, d, k)
        if j in self.convicted:
            return
        other = next(((r2, t) for r2, t in told.items() if t[3] != d and self._valid(j, stamp, t)), None)
        if other is not None and self._valid(j, stamp, told[r]):
            from agents.evidence import _record

            r2, t2 = other
            at = max(k, t2[4])
            self.convicted[j] = at
            self.records.append(_record(self.run_id, j, stamp, at, (r2, *t2[:4]), (r, *told[r][:4])))

    def _valid(self, j: int, stamp: int, t: tuple[int | None, bytes, bytes, bytes, int]) -> bool:
        pub = self.keys.get(f"agent-{j}")
        self.verifications += 1
        ok = pub is not None and verify(pub, t[2], self.run_id, KIND, j, t[0], stamp, t[1])
        self.bad_signatures += not ok
        return ok

    def write(self, run_dir: Path) -> Path:
        from agents.evidence import EVIDENCE_FILE

        path = Path(run_dir) / EVIDENCE_FILE
        path.write_text("".join(json.dumps(r) + "\n" for r in self.records))
        return path

    def report(self, summary: dict[str, Any], run_dir: Path | None, dashboard: Any = None) -> None:
        """Into ``summary`` (``evidence``: :meth:`summary`), ``run_dir/evidence.jsonl`` and the
        dashboard's ``events/convictions`` (at each round of conviction)."""
        summary["evidence"] = self.summary()
        if run_dir is not None:
            self.write(run_dir)
        for j, k in self.convicted.items():
            if hasattr(dashboard, "log_conviction"):
                dashboard.log_conviction(j, k)

    def summary(self) -> dict[str, Any]:
        """``summary.json``'s ``evidence`` (as the simulator's, plus the copies compared)."""
        return {"convicted": {str(j): k for j, k in sorted(self.convicted.items())},
                "bad_signatures": self.bad_signatures, "verifications": self.verifications, "copies": self.copies}


def signing_for(part: Any, cfg: Any, run_id: str, *, regular: bool) -> Signing:
    """The :class:`Signing` of an agent's slice (with ``cfg.sign``; else one that signs nothing)."""
    if not getattr(cfg, "sign", None):
        return Signing(run_id, part.agent_id)
    from transport.signing import load_signer

    try:
        return Signing(run_id, part.agent_id, load_signer(cfg.sign, f"agent-{part.agent_id}"), regular=regular)
    except ValueError as exc:
        raise ScenarioError(f"--sign: {exc}") from None


def convictions_for(exp: Any, cfg: Any, run_id: str) -> Convictions | None:
    """The monitor's :class:`Convictions` with ``cfg.sign`` (else None)."""
    if not getattr(cfg, "sign", None):
        return None
    from transport.signing import load_public_keys

    try:
        keys = load_public_keys(cfg.sign)
    except ValueError as exc:
        raise ScenarioError(f"--sign: {exc}") from None
    regular = {a for i, a in enumerate(exp.agent_ids) if i not in exp.byzantine}
    return Convictions(run_id, keys, regular)
