"""Opening Zenoh sessions (zenoh-python 1.x): peer mode on loopback, or client of a router.

Two deployments, one factory::

    # peers on one machine (the default): no router, no multicast scouting; every
    # process listens on its own loopback port and connects to the ports it is told
    opts = SessionOptions.peer(listen_port=7451, connect_ports=[7450])
    # across hosts: a client of a Zenoh router (zenohd) at HOST:PORT
    opts = SessionOptions.client(["tcp/10.0.0.5:7447"])

    with open_session(opts) as session:      # zenoh.Session; closed on every path
        ...

Multicast scouting is off, so two teams on one machine never find each other; gossip
scouting stays on by default, so a peer that connects to one member of its team learns the
others' (loopback) locators and the peers form a mesh. With ``gossip=False`` a peer is
linked to exactly the peers it connects to (and those that connect to it): ``rse run``
links each agent to the plant, the monitor and its graph neighbours only, not to the whole
team. A peer's ``connect`` endpoints need not be up yet: Zenoh retries them in the
background (every ``retry_ms`` at first, backing off to 1 s, with ``retry_ms`` given). A client whose router is unreachable fails
at once with :class:`~estimation.errors.TransportError`.

A session left open keeps Zenoh's non-daemon callback threads alive and hangs the
interpreter at exit. Every session opened here is therefore also closed by a hook that
runs *before* the interpreter joins its threads (``threading._register_atexit``, the
hook ``concurrent.futures`` uses); this is a safety net, not a substitute for ``with``.
"""

from __future__ import annotations

import atexit
import json
import logging
import os
import re
import socket
import threading
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import zenoh

from estimation.errors import TransportError

__all__ = [
    "LOOPBACK",
    "MODES",
    "SessionOptions",
    "free_tcp_port",
    "tcp_endpoint",
    "normalize_endpoint",
    "is_loopback",
    "make_config",
    "open_session",
    "close_session",
    "HANDED_OVER",
    "ONE_THREAD_RUNTIME",
    "one_zenoh_thread",
    "thread_counts",
]

log = logging.getLogger(__name__)

LOOPBACK = "127.0.0.1"
SMALL_BATCH = 16384  # bytes: a link's batch and receive buffer with small_links
MODES = frozenset({"peer", "client", "router"})
_ENDPOINT_RE = re.compile(r"(tcp|udp|tls|quic|ws|unixsock-stream)/[^\s\"'\\]+\Z")

#: Zenoh's receive, transmit, network and accept runtimes (their threads are named ``rx-0``,
#: ...; Zenoh's default: ``app``, ``acc``, ``tx`` and ``net`` one thread each, ``rx`` two)
HANDED_OVER = ("rx", "tx", "net", "acc")
#: ``ZENOH_RUNTIME`` (RON) that hands those runtimes over to the application runtime, whose
#: one worker thread then does all of a session's work
ONE_THREAD_RUNTIME = "(" + ", ".join(f"{rt}: (handover: app)" for rt in HANDED_OVER) + ")"
ZENOH_RUNTIME_ENV = "ZENOH_RUNTIME"


def one_zenoh_thread() -> bool:
    """Give this process's Zenoh one worker thread (:data:`ONE_THREAD_RUNTIME`), unless the
    environment sets ``ZENOH_RUNTIME`` (``ZENOH_RUNTIME='()'``: Zenoh's own threads).

    Call it before the process's first session: Zenoh reads the variable once, when it
    starts its runtimes. Returns whether it set the variable. The roles of ``rse run`` call
    it: on a machine with fewer cores than busy processes, one thread per process that both
    receives and sends saves the hand-overs between Zenoh's threads.
    """
    if ZENOH_RUNTIME_ENV in os.environ:
        return False
    os.environ[ZENOH_RUNTIME_ENV] = ONE_THREAD_RUNTIME
    return True


def thread_counts() -> dict[str, int]:
    """Threads of this process now: ``threads`` (Python's and Zenoh's; from ``/proc/self/task``,
    else Python's alone) and ``zenoh_io_threads``, those of the :data:`HANDED_OVER` runtimes
    (0 after :func:`one_zenoh_thread`)."""
    try:
        tasks = os.listdir("/proc/self/task")
    except OSError:
        return {"threads": threading.active_count()}
    prefixes = tuple(f"{rt}-" for rt in HANDED_OVER)
    io = 0
    for t in tasks:
        try:
            with open(f"/proc/self/task/{t}/comm") as f:
                io += f.read().startswith(prefixes)
        except OSError:  # the thread ended meanwhile
            pass
    return {"threads": len(tasks), "zenoh_io_threads": io}


def free_tcp_port(host: str = LOOPBACK) -> int:
    """A TCP port on ``host`` that was free a moment ago (bind to port 0, close).

    Another process may take it before it is used; a launcher that starts several
    processes should pick all ports first and treat "address in use" at open time as a
    retryable :class:`TransportError`.
    """
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def tcp_endpoint(port: int, host: str = LOOPBACK) -> str:
    """``tcp/HOST:PORT`` (IPv6 hosts in brackets)."""
    if type(port) is not int or not 0 <= port <= 65535:
        raise ValueError(f"port must be an int in [0, 65535], got {port!r}")
    if ":" in host and not host.startswith("["):
        host = f"[{host}]"
    return f"tcp/{host}:{port}"


def any_port(endpoint: str) -> str:
    """``endpoint`` (``tcp/HOST:PORT``) with port 0: the same host, a port the OS chooses."""
    head, sep, _port = endpoint.rpartition(":")
    return f"{head}:0" if sep and "/" in head else endpoint


def is_loopback(endpoint: str) -> bool:
    """Whether ``endpoint`` (``PROTO/HOST:PORT``) names this host only (127.0.0.0/8, ::1,
    ``localhost``); a name or an address of any other host is not."""
    import ipaddress

    host = endpoint.partition("/")[2].rpartition(":")[0].strip("[]") or endpoint
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def normalize_endpoint(endpoint: str) -> str:
    """Validate a Zenoh endpoint; ``HOST:PORT`` without a protocol means ``tcp/HOST:PORT``.

    Raises ``ValueError`` naming the endpoint and the expected form.
    """
    if not isinstance(endpoint, str):
        raise ValueError(f"endpoint must be a str like 'tcp/HOST:PORT', got {endpoint!r}")
    ep = endpoint.strip()
    if "/" not in ep:
        ep = f"tcp/{ep}"
    if not _ENDPOINT_RE.match(ep):
        raise ValueError(f"invalid Zenoh endpoint {endpoint!r}: expected e.g. 'tcp/127.0.0.1:7447'")
    if ep.startswith(("tcp/", "udp/")) and not re.search(r":\d{1,5}(\?.*|#.*)?\Z", ep):
        raise ValueError(f"invalid Zenoh endpoint {endpoint!r}: expected a port, e.g. 'tcp/HOST:7447'")
    return ep


@dataclass(frozen=True)
class SessionOptions:
    """How to open a session; picklable, so a launcher can hand it to spawned children.

    Attributes
    ----------
    mode : {"peer", "client", "router"}
        ``peer`` (default, no router needed), ``client`` (through a router) or
        ``router`` (mostly for tests that need a router without installing zenohd).
    listen : tuple of str
        Endpoints to listen on. ``None`` means: a peer or router listens on
        ``tcp/127.0.0.1:0`` (loopback, a port chosen by the OS); a client listens on
        nothing.
    connect : tuple of str
        Endpoints of peers or routers to connect to (required for a client).
    multicast_scouting : bool
        Off by default: teams on one machine must not discover each other.
    tls : transport.secure.TlsFiles, optional
        This process's TLS identity (CA, certificate, key): mutual TLS on every link;
        ``tcp/`` endpoints become ``tls/``, other protocols are refused.
    gossip : bool
        Gossip scouting (on: peers learn each other's locators through the ones they
        connect to and form a full mesh; off: only the links configured).
    retry_ms : int, optional
        First retry period of a ``connect`` endpoint that is not up yet (Zenoh's default
        when None: 1 s, backing off to 4 s); the period then grows by half up to 1 s.
    small_links : bool
        Small per-link buffers for many links of small messages: batches of
        :data:`SMALL_BATCH` bytes (larger messages are fragmented) and no shared-memory
        pool (Zenoh's 16 MB pool for messages over 3 kB). QoS stays on: a link keeps one
        transmission queue per priority, so that the droppable messages (their own
        priority, :meth:`transport.zenoh_bus.ZenohBus.publish`) never wait behind a
        blocking one (with one queue per link, a realtime team on a loaded machine saw the
        plant's measurements to some agents dropped for good after the first rounds).
    scout_delay_ms : int, optional
        How long opening a peer session may wait for its ``connect`` endpoints (Zenoh's
        ``scouting/delay``; its default when None: 500 ms whenever one of them is not up
        yet). 0: the session opens at once and the links come up in the background (with
        ``retry_ms``): for a team whose processes start together and wait for each other's
        liveliness anyway.
    acl : dict, optional
        Zenoh's ``access_control`` section, enforced by this session on its own links
        (:func:`transport.secure.peer_access_control`: a secure peer's ingress rules).
    """

    mode: str = "peer"
    listen: tuple[str, ...] | None = None
    connect: tuple[str, ...] = field(default_factory=tuple)
    multicast_scouting: bool = False
    tls: Any = None
    gossip: bool = True
    retry_ms: int | None = None
    small_links: bool = False
    scout_delay_ms: int | None = None
    acl: dict[str, Any] | None = None

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"mode must be one of {sorted(MODES)}, got {self.mode!r}")
        fix = (lambda e: e) if self.tls is None else _secure_endpoint
        if self.listen is not None:
            object.__setattr__(self, "listen", tuple(fix(normalize_endpoint(e)) for e in _seq(self.listen, "listen")))
        object.__setattr__(self, "connect", tuple(fix(normalize_endpoint(e)) for e in _seq(self.connect, "connect")))
        if self.mode == "client" and not self.connect:
            raise ValueError("client mode needs at least one router endpoint in connect (e.g. tcp/HOST:7447)")
        if self.mode == "client" and self.listen:
            raise ValueError("a client does not listen; leave listen empty")

    @classmethod
    def peer(
        cls,
        *,
        listen_port: int | None = None,
        connect_ports: Iterable[int] = (),
        connect: Iterable[str] = (),
        host: str = LOOPBACK,
    ) -> "SessionOptions":
        """Peer on loopback: listen on ``host:listen_port`` (``None``: an OS-chosen port),
        connect to ``host:p`` for each of ``connect_ports`` and to the ``connect`` endpoints.
        """
        listen = (tcp_endpoint(listen_port if listen_port is not None else 0, host),)
        eps = tuple(tcp_endpoint(p, host) for p in connect_ports) + tuple(connect)
        return cls(mode="peer", listen=listen, connect=eps)

    @classmethod
    def client(cls, connect: Iterable[str], tls: Any = None) -> "SessionOptions":
        """Client of the router(s) at ``connect`` (``tcp/HOST:PORT``, or ``HOST:PORT``),
        over mutual TLS with the identity ``tls`` if given."""
        return cls(mode="client", listen=(), connect=tuple(connect), tls=tls)

    def effective_listen(self) -> tuple[str, ...]:
        """The listen endpoints actually configured (see ``listen``)."""
        if self.listen is not None:
            return self.listen
        if self.mode == "client":
            return ()
        return (_secure_endpoint(tcp_endpoint(0)),) if self.tls is not None else (tcp_endpoint(0),)

    def to_config(self) -> zenoh.Config:
        """The ``zenoh.Config`` for these options (see :func:`make_config`)."""
        return make_config(
            mode=self.mode,
            listen=self.effective_listen(),
            connect=self.connect,
            multicast_scouting=self.multicast_scouting,
            tls=self.tls,
            gossip=self.gossip,
            retry_ms=self.retry_ms,
            small_links=self.small_links,
            scout_delay_ms=self.scout_delay_ms,
            acl=self.acl,
        )


def _secure_endpoint(endpoint: str) -> str:
    from transport.secure import secure_endpoint

    return secure_endpoint(endpoint)


def _seq(value: object, what: str) -> Sequence[str]:
    if isinstance(value, str) or not isinstance(value, Iterable):
        raise ValueError(f"{what} must be a sequence of endpoints, got {value!r}")
    return tuple(value)


def make_config(
    *,
    mode: str = "peer",
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    multicast_scouting: bool = False,
    tls: Any = None,
    gossip: bool = True,
    retry_ms: int | None = None,
    small_links: bool = False,
    scout_delay_ms: int | None = None,
    acl: dict[str, Any] | None = None,
) -> zenoh.Config:
    """Build a ``zenoh.Config`` with ``zenoh.Config()`` + ``insert_json5``.

    Sets ``mode``, ``listen/endpoints``, ``connect/endpoints`` and
    ``scouting/multicast/enabled`` (the keys of Zenoh's ``DEFAULT_CONFIG.json5``),
    ``scouting/gossip/enabled`` when ``gossip`` is off, ``connect/retry`` with ``retry_ms``,
    ``scouting/delay`` with ``scout_delay_ms``,
    the link buffers of ``small_links``, and
    with ``tls`` (a :class:`transport.secure.TlsFiles`) the ``transport/link/tls`` keys of
    mutual TLS (:func:`transport.secure.tls_settings`), ``access_control`` with ``acl``; everything
    else keeps Zenoh's defaults. Values are written with ``json.dumps`` (JSON
    is JSON5), so no endpoint string can inject configuration.
    """
    if mode not in MODES:
        raise ValueError(f"mode must be one of {sorted(MODES)}, got {mode!r}")
    listen = [normalize_endpoint(e) for e in _seq(listen, "listen")]
    connect = [normalize_endpoint(e) for e in _seq(connect, "connect")]
    conf = zenoh.Config()
    try:
        conf.insert_json5("mode", json.dumps(mode))
        conf.insert_json5("scouting/multicast/enabled", json.dumps(bool(multicast_scouting)))
        conf.insert_json5("listen/endpoints", json.dumps(listen))
        conf.insert_json5("connect/endpoints", json.dumps(connect))
        if not gossip:
            conf.insert_json5("scouting/gossip/enabled", "false")
        if retry_ms is not None:
            conf.insert_json5("connect/retry", json.dumps({"period_init_ms": int(retry_ms), "period_max_ms": 1000,
                                                           "period_increase_factor": 1.5}))
        if scout_delay_ms is not None:
            conf.insert_json5("scouting/delay", json.dumps(int(scout_delay_ms)))
        if small_links:
            conf.insert_json5("transport/link/tx/batch_size", json.dumps(SMALL_BATCH))
            conf.insert_json5("transport/link/rx/buffer_size", json.dumps(SMALL_BATCH))
            conf.insert_json5("transport/shared_memory/enabled", "false")
        if tls is not None:
            from transport.secure import tls_settings

            for key, value in tls_settings(tls).items():
                conf.insert_json5(key, json.dumps(value))
        if acl is not None:
            conf.insert_json5("access_control", json.dumps(acl))
    except Exception as exc:  # zenoh.ZError: an endpoint Zenoh itself does not accept
        raise ValueError(f"invalid Zenoh configuration: {exc}") from exc
    return conf


# Sessions opened here and not yet known to be closed (see the module docstring).
_open_sessions: list[zenoh.Session] = []
_open_lock = threading.Lock()


def open_session(options: SessionOptions | zenoh.Config | None = None) -> zenoh.Session:
    """Open a Zenoh session; use it as a context manager (``with open_session(...) as s``).

    Parameters
    ----------
    options : SessionOptions or zenoh.Config, optional
        ``None`` means ``SessionOptions()``: a peer on loopback with an OS-chosen port,
        no multicast scouting, connected to nobody.

    Raises
    ------
    TransportError
        Zenoh could not open the session (a listen port already in use, a router that
        cannot be reached in client mode, ...); the message names the endpoints.
    """
    if options is None:
        options = SessionOptions()
    if isinstance(options, SessionOptions):
        config = options.to_config()
        where = f"mode={options.mode} listen={list(options.effective_listen())} connect={list(options.connect)}"
        if options.tls is not None:
            where += f" tls identity {options.tls.identity}"
    elif isinstance(options, zenoh.Config):
        config, where = options, "the given zenoh.Config"
    else:
        raise TypeError(f"open_session expects SessionOptions or zenoh.Config, got {type(options).__name__}")
    try:
        session = zenoh.open(config)
    except Exception as exc:  # zenoh.ZError (subclass of Exception only)
        raise TransportError(f"cannot open a Zenoh session ({where}): {exc}") from exc
    except BaseException as exc:  # a Rust panic (pyo3's PanicException), e.g. a bad ZENOH_RUNTIME
        if type(exc).__name__ != "PanicException":
            raise
        bad = f"; {ZENOH_RUNTIME_ENV}={os.environ[ZENOH_RUNTIME_ENV]!r}" if ZENOH_RUNTIME_ENV in os.environ else ""
        raise TransportError(f"Zenoh failed to start ({where}{bad}): {str(exc).splitlines()[0][:300]}") from None
    with _open_lock:
        _open_sessions[:] = [s for s in _open_sessions if not s.is_closed()]
        _open_sessions.append(session)
    log.debug("zenoh session %s opened (%s)", session.zid(), where)
    return session


def close_session(session: zenoh.Session | None) -> None:
    """Close ``session`` if it is open; never raises (a failure is logged).

    For ``finally`` blocks and shutdown paths where a second error would hide the first.
    """
    if session is None:
        return
    try:
        if not session.is_closed():
            session.close()
    except Exception:
        log.exception("closing a zenoh session failed")
    with _open_lock:
        try:
            _open_sessions.remove(session)
        except ValueError:
            pass


def _close_all_at_exit() -> None:
    with _open_lock:
        sessions, _open_sessions[:] = list(_open_sessions), []
    for s in sessions:
        try:
            if not s.is_closed():
                log.warning("closing a zenoh session left open at interpreter exit")
                s.close()
        except Exception:
            log.exception("closing a zenoh session at exit failed")


def _register_exit_hook() -> None:
    # threading._register_atexit runs before threading._shutdown() joins non-daemon
    # threads (plain atexit hooks run after, too late). CPython-private, hence the fallback.
    register = getattr(threading, "_register_atexit", None)
    if register is not None:
        try:
            register(_close_all_at_exit)
            return
        except RuntimeError:  # interpreter already shutting down
            pass
    atexit.register(_close_all_at_exit)


_register_exit_hook()
