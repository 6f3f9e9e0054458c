"""Equivocation becomes evidence: signed messages, digests compared, convictions proven.

A Byzantine agent may tell different receivers different things for the same round (the
``equivocation`` strategy of :mod:`transport.byzantine`; Mitra et al. allow it). With the
team's signing keys (``rse certs``, :mod:`transport.signing`) that is provable:

1. **Sign once, at the sender.** Every message is signed by its sender over (run, kind,
   sender, receiver, stamp, payload): a broadcast once per round (receiver -1), an
   addressed message once per receiver.
2. **Digest at the receiver.** Each regular receiver keeps, per sender and stamp, the
   16-byte BLAKE2b digest of the payload it was told, with the signed message.
3. **Exchange digests one round later.** In round ``s + 1`` the regular receivers of a
   sender compare their digests of its stamp-``s`` messages. Equal digests: nothing is
   verified (the links are authenticated, see ``docs/deployment.md``). Two different
   digests: both signed messages are verified against the sender's public key; if both
   verify, the sender is **convicted at round s + 1** and an evidence record (both signed
   messages) is written to ``evidence.jsonl``; a message whose signature fails is a
   forgery nobody can pin on the sender and is counted (``bad_signatures``).

So signatures cost one signing per sent message and, per conflict, one verification per
receiver's copy, not one verification per received message. A regular agent sends one value per round to
everyone: its digests never differ, it cannot be convicted. Anyone holding the team's
public keys checks a record offline (:func:`verify_record`, ``rse verify-evidence``).

With ``ignore_convicted`` the receivers drop a convicted sender's later messages (off by
default: a paper's algorithm runs as written).
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

from transport.signing import digest, payload_bytes, verify

from .rounds import addressed

__all__ = ["EquivocationWatch", "watch_for", "verify_record", "verify_file", "EVIDENCE_FILE"]

EVIDENCE_FILE = "evidence.jsonl"
KIND = "est"


class EquivocationWatch:
    """The signing, digests and convictions of one team (the simulator's hook).

    Parameters
    ----------
    run_id : str
        What every signature binds the messages to.
    signers : mapping agent id -> :class:`transport.signing.Signer`
        Each agent's signing key (the simulator signs for each sender with its own key).
    public_keys : mapping identity -> Ed25519 public key
        The team's (``agent-{id}``), to verify on conflict.
    regular : iterable of int
        The receivers that exchange digests (a Byzantine receiver is not asked).
    ignore_convicted : bool
        Drop a convicted sender's messages from the round after its conviction.
    """

    def __init__(self, run_id: str, signers: dict[int, Any], public_keys: dict[str, Any], regular: Iterable[int],
                 *, ignore_convicted: bool = False) -> None:
        self.run_id, self.signers, self.keys = run_id, signers, public_keys
        self.regular = set(regular)
        self.ignore_convicted = ignore_convicted
        self.told: dict[tuple[int, int], dict[int, tuple[int | None, bytes, bytes, bytes]]] = {}
        self.convicted: dict[int, int] = {}
        self.records: list[dict[str, Any]] = []
        self.bad_signatures = 0
        self.signatures = self.verifications = 0
        self._round = -1

    # ----------------------------------------------------------------- the driver's hook
    def deliver(self, node: Any, k: int, msg: Any, targets: list[Any]) -> None:
        """:func:`agents.simulate.deliver` with signatures and digests: hand ``node``'s
        round-``k`` message(s) to ``targets`` (the digests of round ``k - 1`` are compared
        first, once per round)."""
        if k != self._round:
            self.exchange(k)
        j = node.id
        if self.ignore_convicted and j in self.convicted:
            return
        if isinstance(msg, dict):
            by_id = {t.id: t for t in targets}
            for r, stamp, value in addressed(msg, k, by_id):
                self._note(j, r, r, stamp, value)
                by_id[r].receive(j, stamp, value)
            return
        payload = payload_bytes(msg)
        sig = self._sign(j, None, k, payload)
        d = digest(payload)
        for tgt in targets:
            if tgt.id in self.regular:
                self.told.setdefault((j, k), {})[tgt.id] = (None, payload, sig, d)
            tgt.receive(j, k, msg)

    def _sign(self, j: int, receiver: int | None, stamp: int, payload: bytes) -> bytes:
        self.signatures += 1
        return self.signers[j].sign(self.run_id, KIND, j, receiver, stamp, payload)

    def _note(self, j: int, r: int, field: int | None, stamp: int, value: Any) -> None:
        payload = payload_bytes(value)
        sig = self._sign(j, field, stamp, payload)
        if r in self.regular:
            self.told.setdefault((j, stamp), {})[r] = (field, payload, sig, digest(payload))

    # ----------------------------------------------------------------- the exchange
    def exchange(self, k: int) -> None:
        """Round ``k``: the regular receivers compare their digests of every stamp before
        ``k`` still held; a conflict is verified and may convict (at round ``k``)."""
        self._round = k
        for key in [key for key in self.told if key[1] < k]:
            told = self.told.pop(key)
            if len({t[3] for t in told.values()}) > 1 and key[0] not in self.convicted:
                self._conflict(key[0], key[1], told, k)

    def finish(self, k_last: int) -> None:
        """After the last round ``k_last``: its digests are compared too (round ``k_last + 1``)."""
        self.exchange(k_last + 1)

    def _conflict(self, j: int, stamp: int, told: dict[int, tuple[int | None, bytes, bytes, bytes]], k: int) -> None:
        pub = self.keys.get(f"agent-{j}")
        valid = []
        for r, (field, payload, sig, d) in sorted(told.items()):
            self.verifications += 1
            if pub is not None and verify(pub, sig, self.run_id, KIND, j, field, stamp, payload):
                valid.append((r, field, payload, sig, d))
            else:
                self.bad_signatures += 1
        for a in valid:
            b = next((b for b in valid if b[4] != a[4]), None)
            if b is not None:
                self.convicted[j] = k
                self.records.append(_record(self.run_id, j, stamp, k, a, b))
                return

    def write(self, run_dir: Path) -> Path:
        """Write ``run_dir/evidence.jsonl`` (one record per convicted agent)."""
        path = Path(run_dir) / EVIDENCE_FILE
        path.write_text("".join(json.dumps(r) + "\n" for r in self.records))
        return path

    def summary(self) -> dict[str, Any]:
        """``summary.json``'s ``evidence``: the convicted agents and their round of conviction."""
        return {"convicted": {str(j): k for j, k in sorted(self.convicted.items())},
                "bad_signatures": self.bad_signatures, "signatures": self.signatures,
                "verifications": self.verifications}


def watch_for(exp: Any, certs: str | Path, run_id: str, *, ignore_convicted: bool = False) -> EquivocationWatch:
    """The watch of experiment ``exp`` with the keys of ``rse certs`` in ``certs`` (every
    agent's signing key and public key); ``ValueError`` naming a missing key file."""
    from transport.signing import load_public_keys, load_signer

    keys = load_public_keys(certs)
    signers = {a: load_signer(certs, f"agent-{a}") for a in exp.agent_ids}
    regular = [a for i, a in enumerate(exp.agent_ids) if i not in exp.byzantine]
    return EquivocationWatch(run_id, signers, keys, regular, ignore_convicted=ignore_convicted)


def _message(field: int | None, payload: bytes, sig: bytes) -> dict[str, Any]:
    shape_json, _, data = payload.partition(b"\0")
    x = np.frombuffer(data, dtype="<f8").reshape(json.loads(shape_json))
    return {"receiver": field, "x": x.tolist(), "signature": sig.hex()}


def _record(run: str, j: int, stamp: int, k: int, a: tuple, b: tuple) -> dict[str, Any]:
    return {"run": run, "kind": KIND, "sender": j, "identity": f"agent-{j}", "stamp": stamp, "convicted_at": k,
            "told": [a[0], b[0]], "messages": [_message(a[1], a[2], a[3]), _message(b[1], b[2], b[3])]}


def verify_record(rec: Any, public_keys: dict[str, Any]) -> str | None:
    """None if ``rec`` proves that its sender equivocated (two messages of the same run,
    kind, sender and stamp, different payloads, both signed with the sender's key), else
    what is wrong."""
    try:
        run, kind, j, stamp = str(rec["run"]), str(rec["kind"]), int(rec["sender"]), int(rec["stamp"])
        msgs = rec["messages"]
        if not isinstance(msgs, list) or len(msgs) != 2:
            return "expected two messages"
        if rec.get("identity") != f"agent-{j}":
            return f"identity {rec.get('identity')!r} is not the sender's (agent-{j})"
        if int(rec["convicted_at"]) < stamp:
            return f"convicted at round {rec['convicted_at']}, before the stamp {stamp}"
        told = [int(r) for r in rec["told"]]
        if len(told) != 2 or any(m["receiver"] is not None and int(m["receiver"]) != r for m, r in zip(msgs, told)):
            return "the receivers named do not match the messages"
        pub = public_keys.get(f"agent-{j}")
        if pub is None:
            return f"no public key of agent-{j}"
        payloads = []
        for n, m in enumerate(msgs, 1):
            field = None if m["receiver"] is None else int(m["receiver"])
            payload = payload_bytes(np.asarray(m["x"], dtype=float))
            if not verify(pub, bytes.fromhex(m["signature"]), run, kind, j, field, stamp, payload):
                return f"message {n}: the signature does not verify under agent-{j}'s key"
            payloads.append(payload)
    except (KeyError, TypeError, ValueError) as exc:
        return f"malformed record ({type(exc).__name__}: {exc})"
    if payloads[0] == payloads[1]:
        return "the two messages carry the same values (no equivocation)"
    return None


def verify_file(path: str | Path, public_keys: dict[str, Any]) -> list[tuple[int, dict[str, Any] | None, str | None]]:
    """``(line number, record, None or what is wrong)`` for every non-empty line of ``path``."""
    out: list[tuple[int, dict[str, Any] | None, str | None]] = []
    for n, line in enumerate(Path(path).read_text().splitlines(), 1):
        if not line.strip():
            continue
        try:
            rec = json.loads(line)
        except ValueError as exc:
            out.append((n, None, f"not JSON ({exc})"))
            continue
        out.append((n, rec if isinstance(rec, dict) else None,
                    verify_record(rec, public_keys) if isinstance(rec, dict) else "not a JSON object"))
    return out
