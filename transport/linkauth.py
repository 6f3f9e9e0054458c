"""Who sent this estimate? Pairwise message authentication of a secure team.

Zenoh's access control drops a forbidden put before the application sees it, so a
receiver cannot count what an insider forged. A secure team therefore authenticates its
estimates and done reports itself, at every receiver, and counts every rejection with its
reason (``summary.json``'s ``rejected``):

* **Pairwise keys.** Every two identities ``A`` and ``B`` of the team (``plant``,
  ``monitor``, ``agent-i``) share a 32-byte key: HKDF-SHA256 of the ECDH (P-256) of
  ``A``'s TLS private key and ``B``'s certificate (``rse certs`` writes both; a host needs
  only its own key and the team's public certificates). Nobody else can compute it.
* **One tag per team member.** A sealed message is ``inner || tags || n || MAGIC``: the
  keyed BLAKE2b (16 bytes) of ``h = BLAKE2b(key expression || inner)`` under the key of
  the sender and each of the ``n`` team identities, in :func:`team_identities` order.
  A broadcast's receivers are not known to its sender; each finds its own tag.
* **Checked at every receiver.** A receiver recomputes its tag with the key it shares with
  the sender the key expression names. A mismatch is rejected: ``impersonation`` when the
  tag is another member's (an agent with its own certificate speaking for another; the log
  names both), else ``unauthenticated`` (no trailer, a wrong one, a stranger's).

Cost per message: one BLAKE2b of the message and ``n`` of 32 bytes to seal, two to open
(a few microseconds), against 157 us for an Ed25519 verification: every message is
checked. Only the estimate keys are sealed (:func:`sealed`): ``agent/**`` and
``ctl/done/*``; the other keys stay bound to their certificate by Zenoh's access control.
"""

from __future__ import annotations

import hashlib
import hmac
import struct
from collections.abc import Iterable
from pathlib import Path
from typing import Any

__all__ = ["LinkAuth", "load_link_auth", "team_identities", "sealed", "TAG", "MAGIC", "REASONS"]

TAG = 16
MAGIC = b"\xa7L"
_TRAILER = struct.Struct("<H")
_INFO = b"rse-link-mac-v1\0"
#: the reasons of a rejected message (transport-level names, counted by the roles)
REASONS = ("impersonation", "unauthenticated")


def team_identities(agent_ids: Iterable[int]) -> list[str]:
    """The identities a sealed message carries tags for, in order."""
    return ["plant", "monitor", *(f"agent-{i}" for i in sorted({int(a) for a in agent_ids}))]


def sealed(key: str) -> bool:
    """Whether messages on ``key`` (``rse/{run}/...``) are sealed: estimates and done reports."""
    parts = key.split("/", 4)
    return len(parts) > 3 and (parts[2] == "agent" or (parts[2] == "ctl" and parts[3] == "done"))


class LinkAuth:
    """The pairwise keys of one identity: :meth:`seal` what it sends, :meth:`open` what it hears.

    Parameters
    ----------
    me : str
        This process's identity.
    keys : mapping identity -> bytes
        The key this process shares with each team identity (itself included).
    order : list of str
        :func:`team_identities`: the tags' order (every member must agree on it).
    """

    def __init__(self, me: str, keys: dict[str, bytes], order: list[str]) -> None:
        if me not in order:
            raise ValueError(f"identity {me!r} is not one of the team's ({', '.join(order)})")
        self.me, self.order = me, list(order)
        # keyed BLAKE2b states prepared once: a tag is a copy, an update and a digest
        self._keys = [hashlib.blake2b(key=keys[x], digest_size=TAG) for x in self.order]
        self._by_name = {x: hashlib.blake2b(key=k, digest_size=TAG) for x, k in keys.items()}
        self._mine = self.order.index(me)
        self._suffix = _TRAILER.pack(len(self.order)) + MAGIC
        self.sealed = self.opened = 0

    @staticmethod
    def _h(key: str, inner: bytes) -> bytes:
        return hashlib.blake2b(key.encode() + b"\0" + inner, digest_size=32).digest()

    @staticmethod
    def _tag(k: Any, h: bytes) -> bytes:
        c = k.copy()
        c.update(h)
        return bytes(c.digest())

    def seal(self, key: str, inner: bytes) -> bytes:
        """``inner`` with one tag per team identity (see the module docstring)."""
        h = self._h(key, inner)
        self.sealed += 1
        return b"".join([inner, *(self._tag(k, h) for k in self._keys), self._suffix])

    def open(self, key: str, payload: bytes, claimed: str) -> tuple[bytes | None, str, str | None]:
        """``(inner, "", None)`` if ``payload`` on ``key`` was sealed by ``claimed`` for this
        process, else ``(None, reason, who)``: ``impersonation`` with ``who`` the member whose
        tag it carries, or ``unauthenticated``."""
        n = len(self.order)
        size = n * TAG + _TRAILER.size + len(MAGIC)
        if len(payload) < size or payload[-len(self._suffix):] != self._suffix:
            return None, "unauthenticated", None
        inner, tags = payload[:-size], payload[-size:-size + n * TAG]
        tag = tags[self._mine * TAG:(self._mine + 1) * TAG]
        h = self._h(key, inner)
        k = self._by_name.get(claimed)
        if k is not None and hmac.compare_digest(self._tag(k, h), tag):
            self.opened += 1
            return inner, "", None
        for who, k2 in zip(self.order, self._keys):
            if who != claimed and hmac.compare_digest(self._tag(k2, h), tag):
                return None, "impersonation", who
        return None, "unauthenticated", None


def _ec() -> Any:
    try:
        from cryptography import x509
        from cryptography.hazmat.primitives import hashes, serialization
        from cryptography.hazmat.primitives.asymmetric import ec
        from cryptography.hazmat.primitives.kdf.hkdf import HKDF
    except ImportError:
        raise ImportError("a secure team needs the cryptography package: "
                          "pip install 'resilient-state-estimation[secure]'") from None
    return x509, hashes, serialization, ec, HKDF


def load_link_auth(directory: str | Path, me: str, order: list[str]) -> LinkAuth:
    """The :class:`LinkAuth` of identity ``me``: its TLS key ``DIR/me.key`` and the
    certificates ``DIR/{x}.pem`` of every ``x`` of ``order``; ``ValueError`` naming a missing
    or unreadable file."""
    x509, hashes, serialization, ec, HKDF = _ec()
    d = Path(directory)
    try:
        priv = serialization.load_pem_private_key((d / f"{me}.key").read_bytes(), password=None)
    except (OSError, ValueError) as exc:
        raise ValueError(f"--secure {d}: cannot read {me}.key ({exc})") from None
    if not isinstance(priv, ec.EllipticCurvePrivateKey):
        raise ValueError(f"--secure {d}: {me}.key is not an EC key")
    keys: dict[str, bytes] = {}
    for x in order:
        try:
            pub = x509.load_pem_x509_certificate((d / f"{x}.pem").read_bytes()).public_key()
        except (OSError, ValueError) as exc:
            raise ValueError(f"--secure {d}: cannot read {x}.pem, the certificate of a team member ({exc})") from None
        if not isinstance(pub, ec.EllipticCurvePublicKey) or pub.curve.name != priv.curve.name:
            raise ValueError(f"--secure {d}: {x}.pem is not an EC key on {priv.curve.name}")
        shared = priv.exchange(ec.ECDH(), pub)
        pair = "\0".join(sorted((me, x))).encode()
        keys[x] = HKDF(algorithm=hashes.SHA256(), length=32, salt=None, info=_INFO + pair).derive(shared)
    return LinkAuth(me, keys, order)
