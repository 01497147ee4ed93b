"""The one socket factory: every ZeroMQ socket of the services is made by :func:`open_socket`.

Each socket's high-water mark, LINGER, send policy and (receiving sockets) MAXMSGSIZE come from
the settings; the defaults are named below with their reasons (after GNU Radio's gr-zeromq
``base_impl.cc``). What is logged at start-up is read back from the socket with
``getsockopt``, so the log shows what is in force, not what was asked for.

Binding to port 0 (``tcp://127.0.0.1:0`` or ``tcp://127.0.0.1:*``) takes a free port; the
bound endpoint is the socket's ``LAST_ENDPOINT`` (:func:`bound_endpoint`). A service that binds
writes its bound endpoints to ``MTCW_ENDPOINTS_FILE`` when that is set
(:func:`report_endpoints`), and a parent process (``mtcw run``, the tests) reads them
(:func:`wait_for_endpoints`) instead of guessing a free port.
"""

from __future__ import annotations

import json
import logging
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Optional, Union

import zmq

from .auth import CurveClient, CurveServer, apply_client, apply_server, client_keys, server_keys, terminate

if TYPE_CHECKING:
    from .settings import TransportSettings

log = logging.getLogger("mtcw.sockets")

#: High-water mark (messages) of the frame sockets. A frame is up to tens of MB; a short queue
#: shares frames fairly between workers, and a killed worker takes few with it (the consumer
#: counts them from seq gaps).
DEFAULT_FRAME_HWM = 4
#: High-water mark of the point sockets. A point is about a kilobyte: a deep queue rides out a
#: pause of the API (a slow HTTP client, a garbage collection) without loss.
DEFAULT_POINT_HWM = 1000
#: LINGER (ms) of the frame sockets: 0, so that stopping never blocks on frames nobody takes;
#: frames discarded this way show as seq gaps (the publisher lingers on purpose, and finitely,
#: for its end-of-run notice).
DEFAULT_FRAME_LINGER_MS = 0
#: LINGER (ms) of the worker's point socket: 2 s, so that the last points still reach the API
#: on a clean stop, yet teardown never hangs on an API that is gone.
DEFAULT_POINT_LINGER_MS = 2000
#: How long (ms) a worker waits for the API to take a point before counting it undelivered:
#: long enough for an API restart's reconnect, short enough that a dead API does not stall the
#: worker's frames.
DEFAULT_POINT_SEND_TIMEOUT_MS = 1000
#: MAXMSGSIZE (bytes, per message part) of the frame receivers: 256 MiB, a 4-channel float64
#: record of 2^23 samples. ZeroMQ disconnects a peer that sends more, before allocating it.
DEFAULT_MAX_FRAME_BYTES = 1 << 28
#: MAXMSGSIZE of the API's point receiver: 1 MiB (a point with 100 targets is about 20 kB).
DEFAULT_MAX_POINT_BYTES = 1 << 20

#: LINGER (ms) of receiving sockets: they have nothing outgoing to wait for.
RECEIVER_LINGER_MS = 0

#: ``SNDTIMEO`` values of the send policies: ``drop`` a message the peers cannot take now
#: (counted by the caller, seen as a seq gap downstream) or ``block`` until one takes it.
SEND_POLICY_TIMEOUT_MS = {"drop": 0, "block": -1}

_SENDING = {zmq.PUSH, zmq.PUB}
_NAMES = {zmq.PUSH: "PUSH", zmq.PULL: "PULL", zmq.PUB: "PUB", zmq.SUB: "SUB"}


@dataclass(frozen=True)
class SocketSpec:
    """What one socket is: its role, type, endpoint and options.

    Attributes
    ----------
    role : str
        Name in logs, e.g. ``"frames (acquisition PUSH)"``.
    kind : int
        ``zmq.PUSH``, ``zmq.PULL``, ``zmq.PUB`` or ``zmq.SUB``.
    endpoint : str
        Where to bind or connect (``tcp://host:port``; port 0 or ``*`` to bind a free port).
    bind : bool
        Bind (the stable end) or connect.
    hwm : int
        High-water mark in messages: ``SNDHWM`` of a sending socket, ``RCVHWM`` of a receiving one.
    linger_ms : int
        ``LINGER`` on close (ms; -1 waits for ever, which no default does).
    send_timeout_ms : int, optional
        ``SNDTIMEO`` of a PUSH socket, its policy when no peer can take a message: 0 drops at
        once, -1 blocks, more waits that long and then drops (:func:`policy_name`). A PUB
        socket always drops at its high-water mark.
    max_msg_bytes : int, optional
        ``MAXMSGSIZE`` of a receiving socket (bytes per message part; a peer that sends more is
        disconnected).
    subscribe : bytes, optional
        Topic prefix of a SUB socket.
    field : str, optional
        The settings field the endpoint comes from, named in errors (``frames_endpoint``).
    curve : CurveServer or CurveClient, optional
        CurveZMQ keys (:mod:`services.auth`): a binding socket is a server that checks its peers
        against the allow-list, a connecting one a client of the server whose key it holds.
    """

    role: str
    kind: int
    endpoint: str
    bind: bool
    hwm: int
    linger_ms: int
    send_timeout_ms: Optional[int] = None
    max_msg_bytes: Optional[int] = None
    subscribe: Optional[bytes] = None
    field: str = "endpoint"
    curve: Union[CurveServer, CurveClient, None] = None


class SocketError(ValueError):
    """A socket could not be bound or connected; the message names the settings field."""

    def __init__(self, field: str, message: str, errno: int = 0) -> None:
        super().__init__(f"{field}: {message}")
        self.field = field
        self.errno = errno


def policy_name(send_timeout_ms: int) -> str:
    """``drop``, ``block`` or ``wait N ms, then drop`` for an ``SNDTIMEO`` value."""
    if send_timeout_ms == 0:
        return "drop"
    if send_timeout_ms < 0:
        return "block"
    return f"wait {send_timeout_ms} ms, then drop"


def open_socket(ctx: zmq.Context, spec: SocketSpec,
                on_refused: Optional[Callable[[str], None]] = None) -> zmq.Socket:
    """Make, configure, bind or connect the socket ``spec`` describes, and log what is in force.

    Parameters
    ----------
    ctx : zmq.Context
    spec : SocketSpec
    on_refused : callable(domain), optional
        Called when a CURVE server socket refuses a peer (a service's metric).

    Raises
    ------
    SocketError
        When the endpoint cannot be bound or connected (the socket is closed first); the
        message names the settings field, the role and the endpoint.
    """
    sock = ctx.socket(spec.kind)
    try:
        if isinstance(spec.curve, CurveServer):
            apply_server(ctx, sock, spec.curve, spec.field.removesuffix("_endpoint"), on_refused)
        elif isinstance(spec.curve, CurveClient):
            apply_client(sock, spec.curve)
        sending = spec.kind in _SENDING
        sock.setsockopt(zmq.SNDHWM if sending else zmq.RCVHWM, spec.hwm)
        sock.setsockopt(zmq.LINGER, spec.linger_ms)
        if spec.send_timeout_ms is not None:
            sock.setsockopt(zmq.SNDTIMEO, spec.send_timeout_ms)
        if spec.max_msg_bytes is not None:
            sock.setsockopt(zmq.MAXMSGSIZE, spec.max_msg_bytes)
        if spec.subscribe is not None:
            sock.setsockopt(zmq.SUBSCRIBE, spec.subscribe)
        (sock.bind if spec.bind else sock.connect)(spec.endpoint)
    except zmq.ZMQError as err:
        sock.close(linger=0)
        raise SocketError(spec.field, f"{spec.role} cannot {'bind' if spec.bind else 'connect'} {spec.endpoint}: "
                                      f"{err}", err.errno) from None
    log.info("socket %s: %s", spec.role, json.dumps(socket_options(sock)))
    return sock


def open_sockets(ctx: zmq.Context, specs: list[SocketSpec], own_ctx: bool,
                 on_refused: Optional[Callable[[str], None]] = None) -> list[zmq.Socket]:
    """Open ``specs`` in order (:func:`open_socket`); if one fails, close those already open and,
    when the service made ``ctx`` itself (``own_ctx``), terminate it, then re-raise.

    Raises
    ------
    SocketError, CurveKeyError, zmq.ZMQError
    """
    opened: list[zmq.Socket] = []
    try:
        for spec in specs:
            opened.append(open_socket(ctx, spec, on_refused))
    except (zmq.ZMQError, ValueError):  # SocketError, CurveKeyError
        for sock in opened:
            sock.close(linger=0)
        if own_ctx:
            terminate(ctx)
        raise
    return opened


def socket_options(sock: zmq.Socket) -> dict:
    """The options in force on ``sock``, read back with ``getsockopt``.

    Returns
    -------
    dict
        ``type``, ``endpoint`` (``LAST_ENDPOINT``: the bound or connected one), ``hwm`` (the
        send or receive HWM by the socket's direction), ``linger_ms`` and, where they apply,
        ``policy`` (from ``SNDTIMEO``; PUB always drops) and ``max_msg_bytes`` (``MAXMSGSIZE``,
        -1 = no limit), and ``curve`` (``server``, ``client`` or ``off``).
    """
    kind = sock.getsockopt(zmq.TYPE)
    sending = kind in _SENDING
    out = {"type": _NAMES.get(kind, str(kind)), "endpoint": bound_endpoint(sock),
           "hwm": sock.getsockopt(zmq.SNDHWM if sending else zmq.RCVHWM), "linger_ms": sock.getsockopt(zmq.LINGER)}
    if kind == zmq.PUSH:
        out["policy"] = policy_name(sock.getsockopt(zmq.SNDTIMEO))
    elif kind == zmq.PUB:
        out["policy"] = "drop"
    else:
        out["max_msg_bytes"] = sock.getsockopt(zmq.MAXMSGSIZE)
    mech = sock.getsockopt(zmq.MECHANISM)
    out["curve"] = ("server" if sock.getsockopt(zmq.CURVE_SERVER) else "client") if mech == zmq.CURVE else "off"
    return out


def bound_endpoint(sock: zmq.Socket) -> str:
    """The socket's ``LAST_ENDPOINT``: for ``tcp://127.0.0.1:0`` the port actually bound."""
    return sock.getsockopt(zmq.LAST_ENDPOINT).decode()


# ---------------------------------------------------------------------------------------------
# the six roles, from the settings
def _server(st: TransportSettings) -> Optional[CurveServer]:
    """The binding services' CURVE keys and allow-list, when ``curve_dir`` is set."""
    return server_keys(st.curve_dir) if st.curve_dir is not None else None


def _client(st: TransportSettings) -> Optional[CurveClient]:
    """A connecting service's CURVE identity ``curve_client``, when ``curve_dir`` is set."""
    return client_keys(st.curve_dir, st.curve_client) if st.curve_dir is not None else None


def frames_push(st: TransportSettings) -> SocketSpec:
    """The acquisition node's frame socket to the workers: bound, policy ``drop_policy``."""
    return SocketSpec("frames (acquisition PUSH)", zmq.PUSH, st.frames_endpoint, bind=True, hwm=st.hwm,
                      linger_ms=st.linger_ms, send_timeout_ms=SEND_POLICY_TIMEOUT_MS[st.drop_policy],
                      field="frames_endpoint", curve=_server(st))


def monitor_pub(st: TransportSettings) -> SocketSpec:
    """The acquisition node's frame socket to monitors and recorders: bound, drops at its HWM."""
    return SocketSpec("monitor (acquisition PUB)", zmq.PUB, st.monitor_endpoint, bind=True, hwm=st.hwm,
                      linger_ms=st.linger_ms, field="monitor_endpoint", curve=_server(st))


def frames_pull(st: TransportSettings) -> SocketSpec:
    """A worker's frame socket: connects, holds at most ``hwm`` frames, refuses oversized ones."""
    return SocketSpec("frames (worker PULL)", zmq.PULL, st.frames_endpoint, bind=False, hwm=st.hwm,
                      linger_ms=RECEIVER_LINGER_MS, max_msg_bytes=st.max_frame_bytes, field="frames_endpoint",
                      curve=_client(st))


def monitor_sub(st: TransportSettings, hwm: int | None = None, topic: bytes = b"frame") -> SocketSpec:
    """A monitor's or recorder's frame socket: connects, subscribes to ``topic``."""
    return SocketSpec("monitor (SUB)", zmq.SUB, st.monitor_endpoint, bind=False, hwm=hwm or st.hwm,
                      linger_ms=RECEIVER_LINGER_MS, max_msg_bytes=st.max_frame_bytes, subscribe=topic,
                      field="monitor_endpoint", curve=_client(st))


def points_push(st: TransportSettings) -> SocketSpec:
    """A worker's point socket to the API: connects, waits ``points_send_timeout_ms``, then drops."""
    return SocketSpec("points (worker PUSH)", zmq.PUSH, st.points_endpoint, bind=False, hwm=st.points_hwm,
                      linger_ms=st.points_linger_ms, send_timeout_ms=st.points_send_timeout_ms,
                      field="points_endpoint", curve=_client(st))


def points_pull(st: TransportSettings) -> SocketSpec:
    """The API's point socket: bound, refuses oversized messages."""
    return SocketSpec("points (API PULL)", zmq.PULL, st.points_endpoint, bind=True, hwm=st.points_hwm,
                      linger_ms=RECEIVER_LINGER_MS, max_msg_bytes=st.max_point_bytes, field="points_endpoint",
                      curve=_server(st))


# ---------------------------------------------------------------------------------------------
def report_endpoints(path: Optional[Path], endpoints: dict[str, str]) -> None:
    """Write ``endpoints`` (settings field name -> bound endpoint or URL) to ``path`` as JSON,
    atomically (written aside, then renamed); nothing when ``path`` is None."""
    if path is None:
        return
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(endpoints))
    os.replace(tmp, path)
    log.info("endpoints reported to %s: %s", path, endpoints)


def wait_for_endpoints(path: Path, timeout_s: float, alive: Callable[[], bool] = lambda: True) -> dict[str, str]:
    """The endpoints a child reported to ``path`` (:func:`report_endpoints`), polled until they
    are there.

    Parameters
    ----------
    path : Path
        The child's ``MTCW_ENDPOINTS_FILE``.
    timeout_s : float
        Give up after this long.
    alive : callable, optional
        False once the child has exited (then waiting stops at once).

    Raises
    ------
    TimeoutError
        When nothing was reported in time, or the child exited first.
    """
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            return json.loads(Path(path).read_text())
        except (FileNotFoundError, ValueError):
            pass
        if not alive():
            raise TimeoutError(f"{path}: the process exited before reporting its endpoints")
        if time.monotonic() > deadline:
            raise TimeoutError(f"{path}: no endpoints reported within {timeout_s:.0f} s")
        time.sleep(0.05)
