"""CurveZMQ for every socket of the services, with an allow-list of client keys.

Keys are made by ``mtcw keys DIR`` (:func:`make_keys`, pyzmq's ``zmq.auth`` certificate
files) and found by one setting, ``curve_dir``::

    DIR/server.key, DIR/server.key_secret     the binding services (acquisition node, API)
    DIR/clients/NAME.key_secret               a connecting service's identity (``curve_client``)
    DIR/authorized/NAME.key                   the allow-list: public keys of the clients let in

A binding socket is a CURVE server: it encrypts and refuses every peer whose public key is not
in ``authorized/`` (checked by pyzmq's ZAP handler, :class:`zmq.auth.thread.ThreadAuthenticator`,
one per ZeroMQ context, through a :class:`Gate` per socket that counts whom it let in and whom
it refused). A connecting socket is a CURVE client that knows the server's public key, so it
talks only to the real server: a process squatting on the port cannot complete the handshake
and receives nothing. Without ``curve_dir`` nothing is encrypted or authenticated, and the
settings then refuse any endpoint that is not on this machine (:func:`is_local_endpoint`).

The allow-list is read when a socket is opened; a service must be restarted to see a new key.
"""

from __future__ import annotations

import ipaddress
import logging
import threading
import weakref
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional
from urllib.parse import urlsplit

import zmq
import zmq.auth
from zmq.auth.thread import ThreadAuthenticator

log = logging.getLogger("mtcw.auth")

SERVER = "server"
CLIENTS_DIR = "clients"
AUTHORIZED_DIR = "authorized"
#: client identities made by default by ``mtcw keys``
DEFAULT_CLIENTS = ("worker", "recorder")


class CurveKeyError(ValueError):
    """A CurveZMQ key file is missing or unreadable; the message names the file and the setting."""


@dataclass(frozen=True)
class CurveServer:
    """What a binding socket needs: its key pair and the allow-list of client public keys (Z85)."""

    public: bytes
    secret: bytes
    allowed: frozenset[bytes]


@dataclass(frozen=True)
class CurveClient:
    """What a connecting socket needs: its key pair and the server's public key (Z85)."""

    public: bytes
    secret: bytes
    server_public: bytes


@dataclass
class Gate:
    """The ZAP credentials check of one socket (one ZAP domain): allow-listed keys pass.

    ``accepted`` and ``refused`` count handshakes; ``on_refused(domain)`` is called for each
    refusal (a service's metric). Called from the authenticator's thread.
    """

    domain: str
    allowed: frozenset[bytes]
    on_refused: Optional[Callable[[str], None]] = None
    accepted: int = 0
    refused: int = 0
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def callback(self, domain: str, key: bytes) -> bool:
        ok = key in self.allowed
        with self._lock:
            if ok:
                self.accepted += 1
            else:
                self.refused += 1
        if not ok:
            log.warning("auth: refused a peer with an unknown CURVE key on %s (%s...)", domain, key[:8].decode())
            if self.on_refused is not None:
                self.on_refused(domain)
        return ok


# ---------------------------------------------------------------------------------------------
# key files
def make_keys(directory: Path, clients: tuple[str, ...] = DEFAULT_CLIENTS) -> dict[str, Path]:
    """Make the server key pair and one key pair per client, and allow the clients in.

    Idempotent: keys that exist are kept (delete a file to replace it), so that running it again
    (a container's start-up, say) changes nothing. Secret files are readable by their owner only.

    Returns
    -------
    dict
        The secret-key files written now, by name (``server`` or the client's).
    """
    directory = Path(directory)
    for sub in ("", CLIENTS_DIR, AUTHORIZED_DIR):
        (directory / sub).mkdir(parents=True, exist_ok=True)
    written: dict[str, Path] = {}
    if not (directory / f"{SERVER}.key_secret").exists():
        pub, sec = zmq.auth.create_certificates(directory, SERVER)
        written[SERVER] = Path(sec)
    for name in clients:
        if not name or "/" in name or name.startswith(".") or name == SERVER:
            raise ValueError(f"client name {name!r}: a plain file name other than {SERVER!r} is needed")
        if (directory / CLIENTS_DIR / f"{name}.key_secret").exists():
            continue
        pub, sec = zmq.auth.create_certificates(directory / CLIENTS_DIR, name)
        Path(pub).replace(directory / AUTHORIZED_DIR / f"{name}.key")
        written[name] = Path(sec)
    for sec in directory.rglob("*.key_secret"):
        sec.chmod(0o600)
    return written


def _load(path: Path, need_secret: bool) -> tuple[bytes, Optional[bytes]]:
    try:
        pub, sec = zmq.auth.load_certificate(path)
    except (OSError, ValueError) as err:
        raise CurveKeyError(f"curve_dir: cannot read {path}: {err} (make keys with `mtcw keys DIR`)") from None
    if need_secret and not sec:
        raise CurveKeyError(f"curve_dir: {path} holds no secret key")
    return pub, sec


def server_keys(directory: Path) -> CurveServer:
    """The binding services' keys and the allow-list from ``directory`` (see the module docstring)."""
    directory = Path(directory)
    pub, sec = _load(directory / f"{SERVER}.key_secret", need_secret=True)
    auth_dir = directory / AUTHORIZED_DIR
    if not auth_dir.is_dir():
        raise CurveKeyError(f"curve_dir: {auth_dir} is missing (the allow-list of client keys)")
    try:
        allowed = frozenset(zmq.auth.load_certificates(auth_dir))
    except (OSError, ValueError) as err:
        raise CurveKeyError(f"curve_dir: {auth_dir}: {err}") from None
    bad = sorted(k for k in allowed if len(k) != 40)  # a Z85 public key is 40 characters
    if bad:
        raise CurveKeyError(f"curve_dir: {auth_dir} holds a key that is not a 40-character Z85 public key: "
                            f"{bad[0][:50]!r}")
    if not allowed:
        log.warning("auth: %s allows no client: every peer will be refused", auth_dir)
    return CurveServer(pub, sec, allowed)  # type: ignore[arg-type]


def client_keys(directory: Path, name: str) -> CurveClient:
    """Client ``name``'s keys and the server's public key from ``directory``."""
    directory = Path(directory)
    pub, sec = _load(directory / CLIENTS_DIR / f"{name}.key_secret", need_secret=True)
    server_pub, _ = _load(directory / f"{SERVER}.key", need_secret=False)
    return CurveClient(pub, sec, server_pub)  # type: ignore[arg-type]


# ---------------------------------------------------------------------------------------------
# sockets
_AUTHENTICATORS: "weakref.WeakKeyDictionary[zmq.Context, ThreadAuthenticator]" = weakref.WeakKeyDictionary()
_AUTH_LOCK = threading.Lock()


def authenticator(ctx: zmq.Context) -> ThreadAuthenticator:
    """The context's ZAP handler (one per context, started on first use)."""
    with _AUTH_LOCK:
        auth = _AUTHENTICATORS.get(ctx)
        if auth is None or not auth.is_alive():
            auth = ThreadAuthenticator(ctx, log=logging.getLogger("mtcw.auth.zap"))
            auth.start()
            _AUTHENTICATORS[ctx] = auth
        return auth


def stop_authenticator(ctx: zmq.Context) -> None:
    """Stop the context's ZAP handler, if it has one (before the context is destroyed)."""
    with _AUTH_LOCK:
        auth = _AUTHENTICATORS.pop(ctx, None)
    if auth is not None:
        auth.stop()


def terminate(ctx: zmq.Context) -> None:
    """Stop the context's ZAP handler, then terminate the context: ``term()`` waits for every
    socket's LINGER (queued messages still go out), and would wait for ever on the handler's own
    sockets."""
    stop_authenticator(ctx)
    ctx.term()


def apply_server(ctx: zmq.Context, sock: zmq.Socket, keys: CurveServer, domain: str,
                 on_refused: Optional[Callable[[str], None]] = None) -> Gate:
    """Make ``sock`` (not yet bound) a CURVE server whose peers are checked by a :class:`Gate`."""
    gate = Gate(domain, keys.allowed, on_refused)
    authenticator(ctx).configure_curve_callback(domain, credentials_provider=gate)
    sock.setsockopt(zmq.ZAP_DOMAIN, domain.encode())
    sock.setsockopt(zmq.ZAP_ENFORCE_DOMAIN, 1)  # no ZAP handler (stopped) = no peer, never any peer
    sock.setsockopt(zmq.CURVE_SECRETKEY, keys.secret)
    sock.setsockopt(zmq.CURVE_PUBLICKEY, keys.public)
    sock.setsockopt(zmq.CURVE_SERVER, 1)
    return gate


def apply_client(sock: zmq.Socket, keys: CurveClient) -> None:
    """Make ``sock`` (not yet connected) a CURVE client of the server whose public key it holds."""
    sock.setsockopt(zmq.CURVE_SECRETKEY, keys.secret)
    sock.setsockopt(zmq.CURVE_PUBLICKEY, keys.public)
    sock.setsockopt(zmq.CURVE_SERVERKEY, keys.server_public)


def is_local_endpoint(endpoint: str) -> bool:
    """True for endpoints that never leave this machine: ``ipc://``, ``inproc://`` and TCP on a
    loopback address (``127.0.0.0/8``, ``::1``, ``localhost``); False for ``*``, ``0.0.0.0``, a
    host name or any other address."""
    scheme, _, rest = endpoint.partition("://")
    if scheme in ("ipc", "inproc"):
        return True
    if scheme != "tcp":
        return False
    host = urlsplit(f"//{rest}").hostname or ""
    if ";" in rest:  # tcp://source;destination: judge the destination
        host = urlsplit(f"//{rest.split(';', 1)[1]}").hostname or ""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False
