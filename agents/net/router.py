"""``rse router``: a Zenoh router in a Python process (no ``zenohd`` needed).

A zenoh-python session in ``router`` mode: it listens on its endpoints, routes between
the clients connected to it (plant, monitor, agents started with ``--client --connect``)
and does nothing else. Multicast and gossip scouting are off: clients reach the router by
its address, and two routers on one network never find each other::

    config = router_config(("tcp/0.0.0.0:7447",))
    serve(config, say=print)          # blocks until SIGINT / SIGTERM, session always closed

With ``secure`` (a directory written by ``rse certs``) every endpoint is TLS with mutual
authentication and the router enforces Zenoh's ``access_control`` built by
:func:`transport.secure.access_control` (who may put, subscribe to and receive what).

``rse run --router`` starts one as a child process (:func:`router_entry`) on a free
loopback port and waits for it to be open before it starts the team.
"""

from __future__ import annotations

import json
import logging
import re
import signal
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from types import FrameType
from typing import Any

from estimation.errors import ScenarioError

log = logging.getLogger("rse.router")

#: where ``rse router`` listens by default: every interface (a container's port, another
#: host's clients), Zenoh's own port; use ``--listen tcp/127.0.0.1:7447`` for this host only
DEFAULT_LISTEN = "tcp/0.0.0.0:7447"


def resolve_port_zero(endpoint: str) -> str:
    """``tcp/HOST:0`` (or ``tls/HOST:0``) -> the same with a port that is free now, so that
    the endpoint the router prints is the one it listens on; other endpoints unchanged."""
    from transport.zenoh_session import free_tcp_port

    proto, _, addr = endpoint.partition("/")
    if proto not in ("tcp", "tls") or not addr.endswith(":0"):
        return endpoint
    host = addr[:-2]
    bare = host[1:-1] if host.startswith("[") else host
    return f"{proto}/{host}:{free_tcp_port(bare or '0.0.0.0')}"


def zenoh_error_line(exc: BaseException) -> str:
    """A Zenoh error as one line: whitespace collapsed, the Rust source location dropped."""
    text = " ".join(str(exc).split())
    return re.sub(r"\s+at \S+\.rs:\d+\.?(?=\]|\s|\Z)", "", text).rstrip(".") + "."


def _base_config(config_file: Path | None) -> Any:
    """``zenoh.Config()``, or the one of a user's file (a bad file is one line naming it)."""
    import zenoh

    if config_file is None:
        return zenoh.Config()
    path = Path(config_file)
    if not path.is_file():
        raise ScenarioError(f"--config {path}: no such file")
    try:
        return zenoh.Config.from_file(str(path))
    except Exception as exc:  # zenoh.ZError: not JSON5 / YAML, unknown keys, ...
        raise ScenarioError(f"--config {path}: not a valid Zenoh configuration: {zenoh_error_line(exc)}") from None


def _listen_endpoints(listen: Sequence[str], conf: Any) -> list[str]:
    """The endpoints given, else the config file's ``listen/endpoints``, else :data:`DEFAULT_LISTEN`."""
    from transport.zenoh_session import normalize_endpoint

    try:
        eps = [normalize_endpoint(e) for e in listen]
    except ValueError as exc:
        raise ScenarioError(f"--listen: {exc}") from None
    if eps:
        return eps
    try:
        found = json.loads(str(conf)).get("listen", {}).get("endpoints") or []
    except ValueError:
        found = []
    if isinstance(found, dict):  # per-mode form {router: [...], peer: [...]}
        found = found.get("router") or []
    return list(found) or [DEFAULT_LISTEN]


def router_config(
    listen: Sequence[str] = (),
    *,
    config_file: Path | None = None,
    secure: Any = None,
    agent_ids: Sequence[int] | None = None,
    run_id: str = "*",
) -> tuple[Any, tuple[str, ...]]:
    """The ``zenoh.Config`` of a router, and the endpoints it will listen on.

    Parameters
    ----------
    listen : sequence of str
        Endpoints (``tcp/HOST:PORT``; ``HOST:PORT`` means tcp). Empty: the config file's
        ``listen/endpoints``, else :data:`DEFAULT_LISTEN`. A port 0 is replaced by a free
        port. With ``secure``, ``tcp/`` endpoints become ``tls/``.
    config_file : Path, optional
        A Zenoh configuration file (JSON5, JSON or YAML) loaded first; ``mode``, the
        listen endpoints, scouting and (with ``secure``) TLS and ``access_control`` are
        then set on top of it.
    secure : transport.secure.TlsFiles, optional
        The router's CA, certificate and key: TLS with mutual authentication and the
        access control of :func:`transport.secure.access_control`.
    agent_ids : sequence of int, optional
        With ``secure``: the agents the access control knows (default: every
        ``agent-{i}.pem`` next to the router's certificate).
    run_id : str
        With ``secure``: restrict the rules to this run (default ``*``: any run).

    Raises
    ------
    ScenarioError
        A bad endpoint or config file, missing certificates (one line naming it).
    """
    from transport import secure as sec

    conf = _base_config(config_file)
    eps = _listen_endpoints(listen, conf)
    if secure is not None:
        try:
            eps = [sec.secure_endpoint(e) for e in eps]
        except ValueError as exc:
            raise ScenarioError(f"--listen: {exc}") from None
    eps = [resolve_port_zero(e) for e in eps]
    settings: dict[str, Any] = {
        "mode": "router",
        "listen/endpoints": eps,
        "scouting/multicast/enabled": False,
        "scouting/gossip/enabled": False,
    }
    if secure is not None:
        ids = list(agent_ids) if agent_ids is not None else sec.agent_ids_in(Path(secure.cert).parent)
        if not ids:
            raise ScenarioError(f"--secure {Path(secure.cert).parent}: no agent-{{i}}.pem certificates there, so "
                                "the access control would admit no agent (run `rse certs DIR --scenario ...`)")
        for key, value in sec.tls_settings(secure, listen=True, connect=False).items():
            settings[key] = value
        settings["access_control"] = sec.access_control(ids, run_id=run_id)
    try:
        for key, value in settings.items():
            conf.insert_json5(key, json.dumps(value))
    except Exception as exc:  # zenoh.ZError: a value Zenoh itself does not accept
        raise ScenarioError(f"invalid router configuration ({key}): {zenoh_error_line(exc)}") from None
    return conf, tuple(eps)


def serve(config: Any, endpoints: Sequence[str] = (), *, say: Callable[[str], None] = print,
          stop: threading.Event | None = None, on_open: Callable[[Any], None] | None = None) -> None:
    """Open the router session, then wait until ``stop`` is set; the session is always closed.

    Parameters
    ----------
    config : zenoh.Config
        From :func:`router_config`.
    endpoints : sequence of str
        Its listen endpoints (printed once open, named if it cannot open).
    say : callable
        Where the one-line notices go.
    stop : threading.Event, optional
        Set it to stop. ``None``: SIGINT and SIGTERM set it (main thread only); the
        previous handlers are restored on return.
    on_open : callable, optional
        Called with the open session (the launcher's readiness signal).

    Raises
    ------
    TransportError
        The session could not be opened (an endpoint in use, a bad certificate, ...).
    """
    from estimation.errors import TransportError
    from transport.zenoh_session import close_session, open_session

    handlers: dict[signal.Signals, Callable[[int, FrameType | None], Any] | int | None] = {}
    # a signal handler only notes the signal: Event.set() there could wait forever for the
    # lock the interrupted main thread holds inside Event.wait() (seen: 1 SIGTERM in 30 to
    # 80 on a loaded machine left `rse router` hanging)
    signalled: list[int] = []
    if stop is None:
        stop = threading.Event()
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                handlers[sig] = signal.signal(sig, lambda signum, _frame: signalled.append(signum))
    session = None
    try:
        try:
            session = open_session(config)  # a signal meanwhile only sets `stop`
        except TransportError as exc:
            raise TransportError(f"cannot start the router on {', '.join(endpoints) or 'its endpoints'}: "
                                 f"{zenoh_error_line(exc.__cause__ or exc)}") from None
        if on_open is not None:
            on_open(session)
        for ep in endpoints:
            say(f"rse router: listening on {ep}")
        if not (stop.is_set() or signalled):
            say(f"rse router: open (zid {session.zid()}); Ctrl-C to stop")
        while not (stop.is_set() or signalled):
            time.sleep(0.1)  # a signal's handler runs here; is_set() takes no lock
    finally:
        close_session(session)
        for sig, h in handlers.items():
            signal.signal(sig, h)


def router_entry(config_args: dict[str, Any], ready: Any) -> None:
    """Target of the router child process of ``rse run --router`` (spawned).

    ``config_args`` are :func:`router_config`'s keyword arguments; ``ready`` (a
    ``multiprocessing.Event``) is set once the session is open. Exit status 0 after
    SIGTERM / SIGINT, 1 if the router cannot start (one line on stderr).
    """
    import os
    import sys

    from agents.console import error
    from estimation.errors import RSEError

    from .parent import die_with_parent

    die_with_parent()
    code = 0
    try:
        conf, eps = router_config(**config_args)
        serve(conf, eps, say=lambda m: None, on_open=lambda s: ready.set())
    except (RSEError, OSError) as exc:
        error(f"router: {exc}")
        code = 1
    except Exception as exc:  # pragma: no cover - a bug; say it in one line
        error(f"router: internal error: {type(exc).__name__}: {exc}")
        code = 1
    sys.stderr.flush()
    os._exit(code)
