"""The Rider's link: its Zenoh config and session (a bounded handshake, its liveliness token and
deadman heartbeat), and why nothing answers when the session has no link at all.

`zenoh_config` and `open_session` are top-level functions on purpose: the daemon opens its own
sessions the same way: both build on `common/zenoh_session.py`.
"""

from __future__ import annotations

import contextlib
import json
import os
import socket
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path

import zenoh

from ride_machine.common.credentials import RIDER, CredentialError, login
from ride_machine.common.threadstate import keeping_state
from ride_machine.common.zenoh_session import RIDER_SIDE, UnreadableRuntime
from ride_machine.common.zenoh_session import open_session as shared_open
from ride_machine.common.zenoh_session import zenoh_config as shared_config
from ride_machine.schema.rider import (
    ANONYMOUS,
    HEARTBEAT_INTERVAL_S,
    alive_key,
    heartbeat_key,
    login_ok,
    rider_id,
)

from .confirm import Confirmations, Ledger
from .discovery import DISCOVERY_MIN_S, PROBE_TIMEOUT_S, Discovery, discover
from .errors import BadCredentials, BadRuntime, BusError, MachineTimeout, RiderError

DEFAULT_CONNECT = "tcp/127.0.0.1:7447"
DEFAULT_TIMEOUT_S = 2.0
OPEN_TIMEOUT_MIN_S = 1.0
HINT_PROBE_S = 0.3


def zenoh_config(
    path: Path | None, connect: Iterable[str] | None, listen: Iterable[str] | None = None
) -> zenoh.Config:
    """A Rider's session config (`common.zenoh_session.RIDER_SIDE`): the shared zenoh.json5
    with the Rider's own endpoints; it listens only when asked, so it never takes the
    daemon's port when both run on one host."""
    try:
        return shared_config(RIDER_SIDE, path, list(listen or []), list(connect or []))
    except CredentialError as exc:
        raise BadCredentials(str(exc)) from exc


def open_session(conf: zenoh.Config, zenoh_threads: int = 1) -> zenoh.Session:
    """A session opened as a Rider opens it: the process's first one lays out Zenoh's runtime
    on `zenoh_threads` worker threads (`common.runtime`; 0: Zenoh's own six), as the daemon
    does: a command's round trip 6-14 % shorter on two cores (BENCHMARKS.md, section 1). A
    `ZENOH_RUNTIME` in the environment wins; one that Zenoh cannot read is `BadRuntime`."""
    try:
        return shared_open(conf, zenoh_threads)
    except UnreadableRuntime as exc:
        raise BadRuntime(str(exc)) from None


def bound_open_timeout(conf: zenoh.Config, timeout: float) -> None:
    """A link's handshake may take the Rider's timeout (at least `OPEN_TIMEOUT_MIN_S`), not
    Zenoh's 10 s: a frozen machine's kernel still accepts the connection, and a handshake
    waiting on it held the session's close, so `rider --timeout 2 status` took 10 s to say so."""
    current = int(json.loads(conf.get_json("transport/unicast/open_timeout") or "10000"))
    wanted = max(round(OPEN_TIMEOUT_MIN_S * 1000), round(timeout * 1000))
    conf.insert_json5("transport/unicast/open_timeout", str(min(current, wanted)))


def rider_login() -> str:
    """`RIDER_ZENOH_USER`, the login in this Rider's keys (`anonymous` without one)."""
    user = login(RIDER)
    if user is None:
        return ANONYMOUS
    if not login_ok(user):
        raise BadCredentials(
            f"RIDER_ZENOH_USER={user!r}: a Rider's login names its keys (rider/<login>/…):"
            " letters, digits and ._@+- only, at most 64"
        )
    return user


def env_connect() -> list[str]:
    """Endpoints from RIDER_CONNECT (comma separated), if set."""
    raw = os.environ.get("RIDER_CONNECT", "")
    return [e.strip() for e in raw.split(",") if e.strip()]


@contextlib.contextmanager
def bus_errors(what: str) -> Iterator[None]:
    """Zenoh's own error (a closed or broken session, a bad key) as a `BusError`."""
    try:
        yield
    except zenoh.ZError as exc:
        raise bus_error(what, exc) from exc


def bus_error(what: str, exc: zenoh.ZError) -> BusError:
    where = str(exc).split(" at /", 1)[0]  # not the Rust source path of the check
    return BusError(f"{what}: {where}")


def direct(callback: Callable[[zenoh.Sample], None]) -> zenoh.handlers.Callback[zenoh.Sample]:
    """Run `callback` on Zenoh's network thread. zenoh-python's default runs each subscriber's
    callback on a thread of its own, so samples of two subscribers (e.g. `status` and `done/*`)
    reach the caller out of the order the machine published them in (~20 % under load). The
    thread keeps its Python state between samples (`common.threadstate`)."""
    return zenoh.handlers.Callback(keeping_state(callback), indirect=False)


class Link:
    """This Rider's Zenoh session, and the options every part of the client reads."""

    def __init__(
        self,
        config_path: Path | None,
        connect: Iterable[str] | None,
        listen: Iterable[str] | None,
        *,
        key_prefix: str,
        timeout: float,
        retries: int,
        supervise: bool,
        zenoh_threads: int,
    ) -> None:
        self.conf = zenoh_config(config_path, connect, listen)
        self.login = rider_login()
        """The login this Rider's keys are under (`rider/<login>/<zid>/…`)."""
        bound_open_timeout(self.conf, timeout)
        self.config_path = config_path
        self.key_prefix = key_prefix
        self.timeout = timeout
        self.retries = retries
        self.supervise = supervise
        self.zenoh_threads = zenoh_threads
        self.rider_id = ""
        self.attachment = b""
        """Who asked, for the machine's event history (sent with every request)."""
        self.ledger = Ledger()
        """The requests this Rider sent, for the machine to confirm (rider/confirm.py)."""
        self.keys: dict[str, zenoh.KeyExpr] = {}
        """Keys declared to the session (`declare_key`): a query on a declared key expression
        is routed without matching its string again (BENCHMARKS.md, section 1)."""
        self._opened_at = 0.0
        self._session: zenoh.Session | None = None
        self._owned = False
        self._token: zenoh.LivelinessToken | None = None
        self._heartbeat: Heartbeat | None = None
        self._confirmations: Confirmations | None = None
        self._confirm_lock = threading.Lock()
        """Held to declare the confirmation queryable (`confirming`) and to end the session, so
        none is declared on a session being closed."""

    def open(self) -> None:
        """Open the session, declare this Rider's liveliness token, start its heartbeat."""
        self._opened_at = time.monotonic()
        try:
            session = open_session(self.conf, self.zenoh_threads)
        except zenoh.ZError as exc:
            # e.g. a client whose router is down: a clear error, not a traceback
            where = str(exc).split(" at /", 1)[0]
            raise MachineTimeout(f"cannot open the Zenoh session: {where}") from exc
        self._session, self._owned = session, True
        self._named(rider_id(self.login, str(session.zid())))
        # The confirmation queryable is declared with the first request (`confirming`).
        self._token = session.liveliness().declare_token(alive_key(self.rider_id))
        if self.supervise:
            self._heartbeat = Heartbeat(session, self.rider_id)

    def borrow(self, session: zenoh.Session) -> None:
        """Use a session opened elsewhere (the gateway's): no token, no heartbeat, and `close`
        leaves it open. The Rider id is the session's own id."""
        self._session, self._owned = session, False
        self._named(str(session.zid()))

    def _named(self, rider: str) -> None:
        self.rider_id = rider
        # The payload's `rider` field means "watch me" and stays unset for one-shot commands;
        # the attachment names who asked, always.
        self.attachment = f"rider={rider}".encode()

    def close(self) -> None:
        """Stop the heartbeat, undeclare the token and the keys, close the session if it is this
        Rider's own (always)."""
        if self._heartbeat is not None:
            self._heartbeat.close()
            self._heartbeat = None
        if self._token is not None:
            self._token.undeclare()
            self._token = None
        with self._confirm_lock:
            if self._confirmations is not None:
                self._confirmations.close()
                self._confirmations = None
            session, self._session = self._session, None
        if session is not None:
            for key_expr in self.keys.values():
                with contextlib.suppress(zenoh.ZError):
                    session.undeclare(key_expr)
        self.keys.clear()
        if session is not None and self._owned:
            session.close()

    @property
    def session(self) -> zenoh.Session:
        if self._session is None:
            raise RiderError("the Rider is not open; use `with Rider(...) as r:`")
        return self._session

    @property
    def is_open(self) -> bool:
        return self._session is not None

    def confirming(self) -> None:
        """Declare this Rider's confirmation queryable (`rider/<login>/<zid>/confirm`) before its
        first request: the machine asks there about every request that names this Rider, and
        one it cannot confirm does not move the machine (it asks again until its
        `bus.confirm_timeout_s` when the declaration arrives after the request). Not at open: a
        Rider that only reads is never asked, and every remote queryable on a key of its own
        left the machine's Zenoh (1.10) ~0.4 KiB the poorer for good after the session closed
        (0.42 KiB per connect under read-only Rider churn, 0.06 without the queryable)."""
        if self._confirmations is not None or not self._owned:
            return  # declared already, or a borrowed session, whose owner answers
        with self._confirm_lock:
            if self._confirmations is None and self._session is not None:
                self._confirmations = Confirmations(self._session, self.rider_id, self.ledger)

    def declare_key(self, key: str) -> None:
        """Declare `key` to this session as a key expression (once); queries ask by it."""
        if key not in self.keys:
            with bus_errors(f"cannot declare {key}"):
                self.keys[key] = self.session.declare_keyexpr(key)

    def time_left(self) -> float:
        """What is left of the timeout since the open began (a session with no link spent 0.5 s
        opening)."""
        return self.timeout - (time.monotonic() - self._opened_at)

    def is_peer(self) -> bool:
        """This session is a peer (Zenoh's default mode), not a client."""
        return bool(json.loads(self.conf.get_json("mode") or '"peer"') == "peer")

    def links_peers(self) -> bool:
        """A peer with gossip on links to the peers gossip names; a client never does."""
        gossip = json.loads(self.conf.get_json("scouting/gossip/enabled") or "true")
        return self.is_peer() and gossip is not False

    def probe(self, endpoint: str) -> zenoh.Session:
        """A short client session to one router (this Rider's config and credentials), for
        the default-machine lookup to ask a router out of its sight (rider/discovery.py)."""
        conf = zenoh_config(self.config_path, [endpoint])
        bound_open_timeout(conf, self.timeout)
        conf.insert_json5("mode", '"client"')
        conf.insert_json5("connect/timeout_ms", str(int(PROBE_TIMEOUT_S * 1000)))
        conf.insert_json5("connect/exit_on_failure", "true")
        return open_session(conf, self.zenoh_threads)

    def lookup(self, settle: float) -> Discovery:
        """The machines alive once discovery has settled for `settle` s (rider/discovery.py),
        within what is left of the timeout since the open began (at least `DISCOVERY_MIN_S`),
        so a frozen machine is told within the timeout."""
        return discover(
            self.session,
            self.key_prefix,
            settle=settle,
            limit=max(DISCOVERY_MIN_S, self.time_left()),
            probe=self.probe,
            links_peers=self.links_peers(),
            peer=self.is_peer(),
        )

    def logs_in(self) -> bool:
        """Whether this session presents a user/password login."""
        return json.loads(self.conf.get_json("transport/auth/usrpwd/user") or "null") is not None

    def no_link_hint(self) -> str:
        """Why nothing answers, when this session has no link at all ("" when it has one).

        A login the machine refuses looks like no machine to Zenoh: the handshake fails and the
        session simply has no peer. Something listening at the endpoint tells the two apart.
        """
        info = self.session.info
        if list(info.peers_zid()) or list(info.routers_zid()):
            return ""
        endpoints = json.loads(self.conf.get_json("connect/endpoints") or "[]")
        if isinstance(endpoints, dict):
            endpoints = [e for group in endpoints.values() for e in group]
        answers = {str(e): _answers(str(e)) for e in endpoints}
        listening = [e for e, live in answers.items() if live]
        if listening and self.logs_in():
            return (
                f"; {', '.join(listening)} answers but refused this session:"
                " authentication refused? (check RIDER_ZENOH_USER and RIDER_ZENOH_PASSWORD_FILE,"
                " and RIDER_ZENOH_TLS_ROOT_CA for tls/)"
            )
        if listening:  # no login of ours to blame (issue 58: an open machine, a link closed)
            return (
                f"; {', '.join(listening)} answers but closed this session, which logs in as"
                " nobody (no RIDER_ZENOH_USER): the machine asks for a login, or it is"
                " restarting"
            )
        silent = [e for e, live in answers.items() if live is None]
        if silent:
            return (
                f"; {', '.join(silent)} accepts connections but never answers"
                " (the machine's process frozen or overloaded?)"
            )
        return f"; nothing answers at {', '.join(map(str, endpoints))} (is the machine up?)"


def _answers(endpoint: str, timeout: float = HINT_PROBE_S) -> bool | None:
    """Whether a process serves a `tcp/` or `tls/` endpoint: True if it reacts to a bad frame
    (a live Zenoh or TLS listener answers or closes at once), None if the connection is
    accepted but nothing comes back (the kernel accepted it for a frozen or stalled process),
    False if nothing accepts it."""
    protocol, _, address = endpoint.partition("/")
    if protocol not in ("tcp", "tls"):
        return False
    host, _, port = address.split("#", 1)[0].rpartition(":")
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=timeout) as sock:
            try:
                sock.sendall(b"\x00\x00")  # an empty Zenoh frame: no handshake starts so
                sock.recv(16)
            except TimeoutError:
                return None
            except OSError:
                return True  # reset: someone is there and refused it
            return True
    except (OSError, ValueError):
        return False


class Heartbeat:
    """A supervising Rider's deadman signal: an empty sample on `rider/<login>/<zid>/heartbeat`
    every `HEARTBEAT_INTERVAL_S`, from its own thread. It stops when the process freezes, dies
    or loses its link, whatever the Zenoh lease says; the machine pauses within
    `rider_loss.timeout_s`."""

    def __init__(
        self, session: zenoh.Session, rider_id: str, interval: float = HEARTBEAT_INTERVAL_S
    ) -> None:
        self.interval = interval
        self._pub = session.declare_publisher(
            heartbeat_key(rider_id),
            congestion_control=zenoh.CongestionControl.DROP,
            priority=zenoh.Priority.DATA_HIGH,
            express=True,
        )
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="rider-heartbeat", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while True:
            with contextlib.suppress(zenoh.ZError):  # a closing session: the loop ends next
                self._pub.put(b"")
            if self._stop.wait(self.interval):
                return

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        with contextlib.suppress(zenoh.ZError):
            self._pub.undeclare()
