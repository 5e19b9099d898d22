"""The Rider client: one method per command, status, IO, diagnostics, `watch()` and `subscribe()`.

It speaks only the wire models in `schema/` over Zenoh. Every command carries a fresh
transaction id; on a timeout the same id is retried, so a retry can never act twice.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import itertools
import json
import logging
import math
import os
import queue
import socket
import threading
import time
import uuid
from collections.abc import AsyncIterator, Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import msgpack
import zenoh
from pydantic import BaseModel, ValidationError

from common.credentials import RIDER, CredentialError, login, zenoh_settings
from common.runtime import first_session_on, unreadable_layout
from common.threadstate import keeping_state
from rider.discovery import (
    MOTION_SETTLE_S,
    PROBE_TIMEOUT_S,
    SETTLE_S,
    Discovery,
    Listing,
    discover,
)
from rider.waiting import Silence
from schema.axes import AxisRecord
from schema.calibration import (
    CalibrationRecord,
    CalibrationSet,
    RotateCalibrationSet,
    TiltCalibrationSet,
)
from schema.codec import (
    MAX_PAYLOAD_BYTES,
    MAX_REPLY_BYTES,
    DecodeError,
    Format,
    decode,
    encode,
    pack,
)
from schema.commands import (
    VALID_FOR_MAX_S,
    CheckResult,
    Command,
    CommandRequest,
    Reply,
    Session,
    StartRequest,
)
from schema.completion import Completion
from schema.diag import CycleDiag
from schema.errors import Error, ErrorCode
from schema.events import Event, EventPage, EventQuery, EventSummary, summarize
from schema.findings import Findings
from schema.io import IoValue
from schema.params import ParamSet, ParamValue
from schema.rider import (
    ANONYMOUS,
    HEARTBEAT_INTERVAL_S,
    alive_key,
    heartbeat_key,
    login_ok,
    rider_id,
)
from schema.sim import SimWorldState
from schema.status import MachineState, Status

M = TypeVar("M", bound=BaseModel)

log = logging.getLogger(__name__)

DEFAULT_CONNECT = "tcp/127.0.0.1:7447"
_MSGPACK = zenoh.Encoding(Format.MSGPACK.value)
"""Prebuilt: a request does not parse its encoding string."""
_ALL = zenoh.ConsolidationMode.NONE
DEFAULT_TIMEOUT_S = 2.0
EMPTY_RETRY_S = 0.05
DONE_RECHECK_S = 1.0
"""`wait_done` asks for the notice this often besides listening for it."""


class RiderError(Exception):
    """Base of every error the Rider client raises."""


class MachineTimeout(RiderError):
    """No reply within the timeout: the machine is gone, or the network is."""


class CommandRefused(RiderError):
    """The machine answered with an error (wrong state, bad payload, ...)."""

    def __init__(self, reply: Reply) -> None:
        error = reply.error or Error(code=ErrorCode.INTERNAL, message="refused without reason")
        where = f" at {error.path}" if error.path else ""
        super().__init__(f"{error.code}: {error.message}{where}")
        self.reply = reply
        self.error = error


class BadCredentials(RiderError):
    """A RIDER_ZENOH_* variable is incomplete or names a file that cannot be read."""


class BadRuntime(RiderError):
    """`ZENOH_RUNTIME` in the environment is a layout Zenoh cannot read."""


class BadReply(RiderError):
    """The machine's reply could not be decoded (version mismatch, corrupt data)."""


class BusError(RiderError):
    """Zenoh refused an operation (a query, a subscription): the session is broken or closed."""


class UnknownTransaction(RiderError):
    """The machine knows no motion with this transaction id (never accepted, forgotten, or
    sent before it restarted): no notice will ever come."""


class DuplicateMachine(RiderError):
    """More than one Zenoh session answers for one machine id (two daemons share it), or one
    other than the session this Rider pinned for it: no answer is "the" answer."""

    def __init__(self, machine_id: str, sessions: Iterable[str], what: str) -> None:
        self.machine_id = machine_id
        self.sessions = tuple(sessions)
        super().__init__(
            f"machine id {machine_id} is answered by more than one session"
            f" ({', '.join(self.sessions)}): {what}; stop one of the daemons or give it another"
            " --id"
        )


class LinkLost(RiderError):
    """`wait_done` heard nothing from the machine for its `link_limit` (the link stayed down)."""


class NoMachine(RiderError):
    """No machine is alive, or the one asked for is not."""


class AmbiguousMachine(RiderError):
    """Several machines are alive and none was named."""


class UnsureMachine(AmbiguousMachine):
    """None was named, and discovery never settled: the Rider cannot tell it heard of all."""


@dataclass(frozen=True)
class MachineInfo:
    """A machine found through its liveliness token."""

    id: str
    state: MachineState | None
    uptime_s: float | None
    sessions: tuple[str, ...] = ()
    """The Zenoh sessions that hold or answer for this id; more than one is a conflict."""

    @property
    def conflict(self) -> bool:
        return len(self.sessions) > 1


Update = Status | IoValue | AxisRecord | CycleDiag | Completion | CalibrationRecord


@dataclass
class _Holders:
    """Who may answer for one machine id: its holder (pinned at first contact) and the
    supervisor that answers while the daemon is down."""

    holders: set[str] = dataclasses.field(default_factory=set)
    supervisors: set[str] = dataclasses.field(default_factory=set)
    pinned: str | None = None
    changes: int = 0
    """How many `update`s ran (counted after each, as a liveliness callback may run one on
    another thread while `Rider._check_repliers` reads)."""
    allowed: zenoh.ZenohId | None = None
    """The replier (its `zenoh.ZenohId`) `Rider._check_repliers` last allowed, valid while
    `changes` is still `allowed_at`: the next reply from it needs no second look."""
    allowed_at: int = -1

    def update(self, kind: str, zid: str, present: bool) -> None:
        group = self.holders if kind == "holder" else self.supervisors
        if present:
            group.add(zid)
        else:
            group.discard(zid)
        if self.pinned not in self.holders and len(self.holders) == 1:
            self.pinned = next(iter(self.holders))  # first contact, or the daemon restarted
        self.changes += 1

    def allows(self, zid: str) -> bool:
        if len(self.holders) > 1:
            return False
        return zid == self.pinned or zid in self.supervisors or self.pinned is None


class Subscription:
    """What `Rider.subscribe` declared; `close()` undeclares it all (also as a context manager)."""

    def __init__(self, entities: list[Any]) -> None:
        self._entities = entities

    def close(self) -> None:
        """Undeclare everything; never raises, so a broken session can still be cleaned up."""
        entities, self._entities = self._entities, []
        for entity in reversed(entities):
            with contextlib.suppress(zenoh.ZError):
                entity.undeclare()

    def __enter__(self) -> Subscription:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


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


def zenoh_config(
    path: Path | None, connect: Iterable[str] | None, listen: Iterable[str] | None = None
) -> zenoh.Config:
    """A Rider's session config: the shared zenoh.json5 with the Rider's own endpoints.

    A Rider connects out and does not listen (unless asked), so it never takes the daemon's
    port when both run on one host.
    """
    conf = zenoh.Config.from_file(str(path)) if path is not None else zenoh.Config()
    if path is None:
        conf.insert_json5("mode", '"peer"')
        conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", json.dumps(list(listen or [])))
    endpoints = list(connect or [])
    if endpoints:
        conf.insert_json5("connect/endpoints", json.dumps(endpoints))
    elif not json.loads(conf.get_json("connect/endpoints") or "[]"):
        conf.insert_json5("connect/endpoints", json.dumps([DEFAULT_CONNECT]))
    try:
        settings = zenoh_settings(RIDER)
    except CredentialError as exc:
        raise BadCredentials(str(exc)) from exc
    for setting, value in settings.items():
        conf.insert_json5(setting, value)
    # A Rider's own admin space stays off: the default-machine lookup reads other nodes' (and
    # zenoh 1.10's token/link-state handlers can wedge a session, rider/discovery.py).
    conf.insert_json5("adminspace/enabled", "false")
    return conf


OPEN_TIMEOUT_MIN_S = 1.0
DISCOVERY_MIN_S = 1.0
"""The default-machine lookup waits at least this long, whatever is left of the timeout."""
HINT_PROBE_S = 0.3


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


def bound_open_timeout(conf: zenoh.Config, timeout: float) -> None:
    """A link's handshake may take the Rider's timeout (at least `OPEN_TIMEOUT_MIN_S`), not
    Zenoh's 10 s: a frozen machine's kernel still accepts the connection, and a handshake
    waiting on it held the session's close, so `rider --timeout 2 status` took 10 s to say so."""
    current = int(json.loads(conf.get_json("transport/unicast/open_timeout") or "10000"))
    wanted = max(round(OPEN_TIMEOUT_MIN_S * 1000), round(timeout * 1000))
    conf.insert_json5("transport/unicast/open_timeout", str(min(current, wanted)))


def open_session(conf: zenoh.Config, zenoh_threads: int = 1) -> zenoh.Session:
    """A session opened as a Rider opens it. The process's first one lays out Zenoh's runtime
    on `zenoh_threads` worker threads (`schema.runtime`; 0: Zenoh's own six), as the daemon
    does: a command's round trip 6-14 % shorter on two cores (BENCHMARKS.md, section 1). A
    `ZENOH_RUNTIME` in the environment wins; one that Zenoh cannot read is `BadRuntime`."""
    with first_session_on(zenoh_threads):
        try:
            return zenoh.open(conf)
        except BaseException as exc:
            if (unreadable := unreadable_layout(exc)) is None:
                raise
            raise BadRuntime(unreadable) from None


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


class Rider:
    """A synchronous Rider session; use as a context manager so the session always closes."""

    def __init__(  # noqa: PLR0913 - the machine, then keyword-only options
        self,
        machine_id: str | None = "m1",
        *,
        connect: Iterable[str] | None = None,
        zenoh_config_path: Path | None = None,
        listen: Iterable[str] | None = None,
        key_prefix: str = "machine",
        timeout: float = DEFAULT_TIMEOUT_S,
        retries: int = 1,
        supervise: bool = True,
        zenoh_threads: int = 1,
    ) -> None:
        """`supervise`: name this Rider in motion commands, so the machine applies its
        rider-loss policy if this process disappears mid-motion (off for one-shot CLI calls).
        `zenoh_threads`: Zenoh's worker threads in this process, as `bus.zenoh_threads` is the
        daemon's (`open_session`; 0 keeps Zenoh's own six)."""
        self.key_prefix = key_prefix
        self.timeout = timeout
        self.retries = retries
        self._conf = zenoh_config(zenoh_config_path, connect, listen)
        self.login = rider_login()
        """The login this Rider's keys are under (`rider/<login>/<zid>/…`)."""
        bound_open_timeout(self._conf, timeout)
        self._conf_path = zenoh_config_path
        self._opened_at = 0.0
        self._session: zenoh.Session | None = None
        self._token: zenoh.LivelinessToken | None = None
        self._heartbeat: Heartbeat | None = None
        self._holders: dict[str, _Holders] = {}
        self._ids = itertools.count(1)
        self._tag = uuid.uuid4().hex[:8]
        self._machine_id = machine_id
        self.discovery: Discovery | None = None
        """What the default-machine lookup saw (None when a machine was named)."""
        self.supervise = supervise
        self.zenoh_threads = zenoh_threads
        self.rider_id = ""
        self._attachment = b""
        self._keys: dict[str, zenoh.KeyExpr] = {}
        """Command keys declared to the session (`_declare_key`): a query on a declared key
        expression is routed without matching its string again (BENCHMARKS.md, section 1)."""
        self._command_keys: dict[Command, str] = {}
        self._machine_of: dict[str, str | None] = {}
        """`_machine_in`'s answers by key (bounded: cleared when it holds `KEY_CACHE` keys)."""
        self._foreign = Throttle(FOREIGN_LOG_EVERY_S)
        """The `foreign_sample` warning: a peer can publish under the machine's keys at any
        rate, and a line per sample cost the Rider's thread more than the sample did."""

    # ---------------------------------------------------------------------------- session
    def open(self) -> Rider:
        self._opened_at = time.monotonic()
        try:
            self._session = open_session(self._conf, self.zenoh_threads)
        except zenoh.ZError as exc:
            # e.g. a client whose router is down: a clear error, not a traceback
            where = str(exc).split(" at /", 1)[0]
            raise MachineTimeout(f"cannot open the Zenoh session: {where}") from exc
        self.rider_id = rider_id(self.login, str(self._session.zid()))
        # What `_own_request` packs without a model, checked once: a tag-and-counter id and
        # this session's id are valid transaction ids.
        CommandRequest(transaction_id=f"{self._tag}-0", rider=self.rider_id)
        # Who asked, for the machine's event history (the payload's `rider` field means
        # "watch me" and stays unset for one-shot commands).
        self._attachment = f"rider={self.rider_id}".encode()
        self._token = self._session.liveliness().declare_token(alive_key(self.rider_id))
        if self.supervise:
            self._heartbeat = Heartbeat(self._session, self.rider_id)
        return self

    def close(self) -> None:
        """Stop the heartbeat, undeclare the liveliness token, close the session (always)."""
        if self._heartbeat is not None:
            self._heartbeat.close()
            self._heartbeat = None
        if self._token is not None:
            self._token.undeclare()
            self._token = None
        if self._session is not None:
            for key_expr in self._keys.values():
                with contextlib.suppress(zenoh.ZError):
                    self._session.undeclare(key_expr)
            self._keys.clear()
            self._command_keys.clear()
            self._session.close()
            self._session = None

    def __enter__(self) -> Rider:
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def no_link_hint(self) -> str:
        """Why nothing answers, when this session has no link at all ("" when it has one).

        A login the machine refuses looks like no machine to Zenoh: the handshake fails and the
        session simply has no peer. Something listening at the endpoint tells the two apart.
        """
        info = self.session.info
        if list(info.peers_zid()) or list(info.routers_zid()):
            return ""
        endpoints = json.loads(self._conf.get_json("connect/endpoints") or "[]")
        if isinstance(endpoints, dict):
            endpoints = [e for group in endpoints.values() for e in group]
        answers = {str(e): _answers(str(e)) for e in endpoints}
        listening = [e for e, live in answers.items() if live]
        if listening:
            return (
                f"; {', '.join(listening)} answers but refused this session:"
                " authentication refused? (check RIDER_ZENOH_USER and RIDER_ZENOH_PASSWORD_FILE,"
                " and RIDER_ZENOH_TLS_ROOT_CA for tls/)"
            )
        silent = [e for e, live in answers.items() if live is None]
        if silent:
            return (
                f"; {', '.join(silent)} accepts connections but never answers"
                " (the machine's process frozen or overloaded?)"
            )
        return f"; nothing answers at {', '.join(map(str, endpoints))} (is the machine up?)"

    @property
    def session(self) -> zenoh.Session:
        if self._session is None:
            raise RiderError("the Rider is not open; use `with Rider(...) as r:`")
        return self._session

    @property
    def machine_id(self) -> str:
        """The machine this Rider talks to: the one named, else the only one alive once
        discovery has settled (`resolve_machine`)."""
        return self.pick_machine()

    def pick_machine(self, *, motion: bool = False) -> str:
        """The machine named, else the default one (looked up once, then kept)."""
        if self._machine_id is None:
            self._machine_id = self.resolve_machine(motion=motion)
        return self._machine_id

    def resolve_machine(self, *, motion: bool = False) -> str:
        """The only machine alive, after discovery settled (rider/discovery.py); raises
        `NoMachine`, `AmbiguousMachine` (several), or `UnsureMachine` (never settled).
        `motion` waits longer (`MOTION_SETTLE_S`) before a command may move a ride."""
        seen = self._discover(MOTION_SETTLE_S if motion else SETTLE_S)
        if not seen.links:
            raise NoMachine(f"no machine is alive on the network{self.no_link_hint()}")
        if not seen.settled:
            raise UnsureMachine(
                f"discovery did not settle within {seen.waited_s:.1f} s, cannot tell which"
                f" machine is the only one ({seen.describe()}); pass --machine ID"
            )
        if seen.unseen and len(seen.alive) <= 1:
            raise UnsureMachine(
                "part of the network is out of sight, cannot tell which machine is the only"
                f" one ({seen.describe()}); connect where it can be seen, or pass --machine ID"
            )
        if not seen.alive:
            raise NoMachine(f"no machine is alive on the network{self.no_link_hint()}")
        if len(seen.alive) > 1:
            ids = ", ".join(sorted(seen.alive))
            raise AmbiguousMachine(f"several machines are alive ({ids}); pass --machine ID")
        return next(iter(seen.alive))

    def _discover(self, settle: float) -> Discovery:
        """Discovery, settled (rider/discovery.py), kept as `self.discovery`."""
        self.discovery = discover(
            self.session,
            self.key_prefix,
            settle=settle,
            # What is left of the timeout since the open began (a session with no link
            # spent 0.5 s opening), so a frozen machine is told within the timeout.
            limit=max(DISCOVERY_MIN_S, self.timeout - (time.monotonic() - self._opened_at)),
            probe=self._probe,
            links_peers=self._links_peers(),
        )
        return self.discovery

    def _links_peers(self) -> bool:
        """A peer with gossip on links to the peers gossip names; a client never does."""
        mode = json.loads(self._conf.get_json("mode") or '"peer"')
        gossip = json.loads(self._conf.get_json("scouting/gossip/enabled") or "true")
        return bool(mode == "peer" and gossip is not False)

    def _probe(self, endpoint: str) -> zenoh.Session:
        """A short client session to one router (this Rider's config and credentials), for
        the default-machine lookup to ask a router out of its sight (rider/discovery.py)."""
        conf = zenoh_config(self._conf_path, [endpoint])
        bound_open_timeout(conf, self.timeout)
        conf.insert_json5("mode", '"client"')
        conf.insert_json5("connect/timeout_ms", str(int(PROBE_TIMEOUT_S * 1000)))
        conf.insert_json5("connect/exit_on_failure", "true")
        return open_session(conf, self.zenoh_threads)

    @property
    def base(self) -> str:
        return f"{self.key_prefix}/{self.machine_id}"

    # --------------------------------------------------------------------------- commands
    def new_transaction_id(self) -> str:
        return f"{self._tag}-{next(self._ids)}"

    def command(
        self,
        command: Command,
        request: CommandRequest | None = None,
        *,
        check: bool = True,
        timeout: float | None = None,
    ) -> Reply:
        """Send one command; raises `CommandRefused` on an error reply when `check`."""
        # A command may move a ride: a default machine is looked up with more certainty.
        self.pick_machine(motion=True)
        # Until when this call waits, counted from the request's timecode (a request sent
        # again later, same transaction, waits anew): a motion command that reaches the
        # machine after that (a frozen daemon resuming) is refused there, not acted unseen.
        wait = (timeout if timeout is not None else self.timeout) * (self.retries + 1)
        if request is None:
            payload = self._own_request(min(wait, VALID_FOR_MAX_S))
        else:
            if request.valid_for is None:
                now = time.time()
                sent = request.timecode if request.timecode is not None else now
                valid = max(now - sent, 0.0) + wait
                request = request.model_copy(update={"valid_for": min(valid, VALID_FOR_MAX_S)})
            payload = encode(request)
        key = self._command_key(command)
        last: RiderError | None = None
        for _ in range(self.retries + 1):
            try:
                reply = self._get_one(key, payload, Reply, timeout)
            except MachineTimeout as exc:
                last = exc  # same transaction id again: at most once on the machine
                continue
            if check and not reply.success:
                raise CommandRefused(reply)
            return reply
        assert last is not None
        raise last

    def _command_key(self, command: Command) -> str:
        """`command`'s key on this Rider's machine, declared (the machine is fixed once
        picked, and so is the prefix: worked out once per command)."""
        key = self._command_keys.get(command)
        if key is None:
            key = f"{self.base}/cmd/{command.key}"
            self._declare_key(key)
            self._command_keys[command] = key
        return key

    def _declare_key(self, key: str) -> None:
        """Declare `key` to this session as a key expression (once); `_get` asks by it."""
        if key not in self._keys:
            with _bus_errors(f"cannot declare {key}"):
                self._keys[key] = self.session.declare_keyexpr(key)

    def _own_request(self, valid_for: float) -> bytes:
        """A plain command's request, packed straight from its fields: the same bytes as
        `encode(CommandRequest(...))` (tests/rider/test_replies.py) without building and
        validating a model per command. Every field is the Rider's own: the id is its tag and a
        counter, the rider its session id (both checked once, at `open`); a `valid_for` that is
        no number in range (a zero timeout) or a Rider not open goes through the model, as
        before."""
        in_range = type(valid_for) in (float, int) and 0 < valid_for <= VALID_FOR_MAX_S
        if not in_range or self._session is None:
            return encode(CommandRequest.model_validate(self._req(valid_for=valid_for)))
        return pack(
            {
                "transaction_id": self.new_transaction_id(),
                "timecode": time.time(),
                "rider": self.rider_id if self.supervise else None,
                "valid_for": float(valid_for),
            }
        )

    def _req(self, **extra: Any) -> dict[str, Any]:
        return {
            "transaction_id": self.new_transaction_id(),
            "timecode": time.time(),
            "rider": self.rider_id if self.supervise else None,
            **extra,
        }

    def calibrate_tilt(self) -> Reply:
        return self.command(Command.CALIBRATE_TILT)

    def calibrate_rotate(self) -> Reply:
        return self.command(Command.CALIBRATE_ROTATE)

    def home(self) -> Reply:
        return self.command(Command.HOME)

    def start(self, session: Session | None = None) -> Reply:
        request = StartRequest.model_validate(self._req(session=session))
        return self.command(Command.START, request)

    def pause(self) -> Reply:
        return self.command(Command.PAUSE)

    def resume(self) -> Reply:
        return self.command(Command.RESUME)

    def stop(self) -> Reply:
        return self.command(Command.STOP)

    def check_calibration(self) -> CheckResult:
        return _result(self.command(Command.CHECK_CALIBRATION))

    def check_home(self) -> CheckResult:
        return _result(self.command(Command.CHECK_HOME))

    # ---------------------------------------------------------------------------- reading
    def status(self, timeout: float | None = None) -> Status:
        return self._get_one(f"{self.base}/status", None, Status, timeout)

    def io(self) -> list[IoValue]:
        points = self._get_all(f"{self.base}/io/**", IoValue)
        return sorted(points, key=lambda p: (p.kind, p.name))

    def axes(self) -> list[AxisRecord]:
        return sorted(self._get_all(f"{self.base}/axis/**", AxisRecord), key=lambda a: a.axis)

    def diag(self, reset: bool = False) -> CycleDiag:
        """The scan loop's diagnostics; `reset` also clears min/max, overruns and missed
        cycles (a command key, `diag/reset`, so the ACL can keep it from read-only identities)."""
        key = f"{self.base}/diag/reset" if reset else f"{self.base}/diag/cycle"
        return self._get_one(key, None, CycleDiag, None)

    def validate(self, candidate: bytes | None = None) -> Findings:
        """Findings for the running config, or for a candidate TOML/JSON config."""
        return self._get_one(f"{self.base}/config/validate", candidate, Findings, None)

    def calibration(self) -> CalibrationRecord:
        """The machine's calibration values: how and when each axis got them."""
        return self._get_one(f"{self.base}/calibration", None, CalibrationRecord, None)

    def set_calibration(
        self,
        *,
        tilt: TiltCalibrationSet | None = None,
        rotate: RotateCalibrationSet | None = None,
    ) -> CalibrationRecord:
        """Enter calibration values by hand (recorded as manual; refused while moving);
        returns the record once the machine has saved them (`CommandRefused` otherwise)."""
        req = CalibrationSet(
            transaction_id=self.new_transaction_id(),
            timecode=time.time(),
            tilt=tilt,
            rotate=rotate,
        )
        key = f"{self.base}/calibration/set"
        return self._get_one(key, encode(req), CalibrationRecord, max(self.timeout, 6.0))

    def params(self) -> list[ParamValue]:
        return sorted(self._get_all(f"{self.base}/params/**", ParamValue), key=lambda p: p.name)

    def param(self, name: str) -> ParamValue:
        return self._get_one(f"{self.base}/params/{name}", None, ParamValue, None)

    def set_param(self, name: str, value: Any, *, persist: bool = False) -> ParamValue:
        req = ParamSet.model_validate(
            {"transaction_id": self.new_transaction_id(), "value": value, "persist": persist}
        )
        return self._get_one(f"{self.base}/params/{name}", encode(req), ParamValue, None)

    def reset_param(self, name: str) -> ParamValue:
        req = ParamSet(transaction_id=self.new_transaction_id(), reset=True)
        return self._get_one(f"{self.base}/params/{name}", encode(req), ParamValue, None)

    def sim(self, fault: str, **payload: Any) -> SimWorldState:
        """Inject a simulator fault (estop, home, tilt_ai, stall, clear) or read the `world`."""
        body = None if fault == "world" else pack(payload)
        return self._get_one(f"{self.base}/sim/{fault}", body, SimWorldState, None)

    # ----------------------------------------------------------------------------- events
    def event_pages(self, query: EventQuery | None = None) -> list[EventPage]:
        """Every page of the history `query` selects, from this machine, or from every machine
        that answers when the machine id is `*` (each machine's pages in order)."""
        return self._pages_from(self.base, query or EventQuery())

    def _pages_from(self, base: str, query: EventQuery) -> list[EventPage]:
        pages: list[EventPage] = []
        pending = [(base, query)]
        while pending:
            base, q = pending.pop(0)
            for page in self._event_query(base, q):
                pages.append(page)
                if page.more and page.next_since is not None:
                    nxt = dataclasses.replace(q, since=page.next_since)
                    pending.append((f"{self.key_prefix}/{page.machine_id}", nxt))
        return pages

    def events(self, query: EventQuery | None = None, **criteria: Any) -> list[Event]:
        """The events `query` (or `EventQuery(**criteria)`) selects, oldest first; with the
        machine id `*`, every machine's, ordered by time."""
        query = query or EventQuery(**criteria)
        found = [e for page in self.event_pages(query) for e in page.events]
        if "*" in self.machine_id:
            found.sort(key=lambda e: (e.time, e.machine_id, e.seq))
        return found

    def events_summary(
        self, since_time: float | None = None, until_time: float | None = None
    ) -> list[EventSummary]:
        """Sessions, ride time, E-stops and faults by code over a time range, per machine."""
        q = EventQuery(since_time=since_time, until_time=until_time)
        by_machine: dict[str, list[Event]] = {}
        for page in self.event_pages(q):
            by_machine.setdefault(page.machine_id, []).extend(page.events)
        return [
            summarize(mid, evs, since_time, until_time) for mid, evs in sorted(by_machine.items())
        ]

    def follow_events(
        self, query: EventQuery | None = None, *, timeout: float | None = None
    ) -> Iterator[Event | None]:
        """The history `query` selects, then each new event as it is written; None after each
        quiet `timeout` (None: wait forever), so the caller can check its own deadline.

        The subscription starts before the history is read, so nothing falls in between; a
        gap in a machine's seq numbers (events published while the link was down, e.g. while
        the daemon restarted) is read from its history before the event after it.
        """
        query = query or EventQuery()
        q: queue.Queue[zenoh.Sample] = queue.Queue(maxsize=65536)

        def on_sample(sample: zenoh.Sample) -> None:
            with contextlib.suppress(queue.Full):
                q.put_nowait(sample)

        with self._declare(("events/*",), on_sample):
            seen: dict[str, int] = {}  # the newest seq received per machine, of any kind
            for event in self.events(query):
                seen[event.machine_id] = event.seq
                yield event
            while True:
                try:
                    sample = q.get(timeout=timeout)
                except queue.Empty:
                    yield None
                    continue
                try:
                    event = _decode_sample(sample, Event, MAX_REPLY_BYTES)
                except BadReply as exc:
                    log.warning("event=bad_event key=%s error=%r", sample.key_expr, str(exc))
                    continue
                newest = seen.get(event.machine_id)
                if newest is not None and event.seq <= newest:
                    continue
                if newest is not None and event.seq > newest + 1:
                    yield from self._missed_events(
                        event.machine_id, newest + 1, event.seq - 1, query
                    )
                seen[event.machine_id] = event.seq
                if query.matches(event):
                    yield event

    def _missed_events(
        self, machine_id: str, first: int, last: int, query: EventQuery
    ) -> list[Event]:
        """The events `query` selects among seq `first`..`last` of one machine, read from its
        history; none (with a warning) if it cannot be read."""
        gap = dataclasses.replace(
            query,
            since=max(first, query.since or 0),
            until=last if query.until is None else min(last, query.until),
            limit=None,
            last=None,
        )
        try:
            pages = self._pages_from(f"{self.key_prefix}/{machine_id}", gap)
        except RiderError as exc:
            log.warning(
                "event=events_gap_unread machine=%s first=%d last=%d error=%r",
                machine_id,
                first,
                last,
                str(exc),
            )
            return []
        return [e for page in pages for e in page.events if e.machine_id == machine_id]

    def _event_query(self, base: str, q: EventQuery) -> list[EventPage]:
        key = f"{base}/events"
        params = q.params()
        selector = f"{key}?{params}" if params else key
        if "*" not in base:
            return [self._get_one(selector, None, EventPage, None)]
        deadline = time.monotonic() + self.timeout
        while True:
            replies = self._get(selector, None, None)
            if replies or time.monotonic() > deadline - EMPTY_RETRY_S:
                return [self._decode(r, EventPage) for r in replies]
            time.sleep(EMPTY_RETRY_S)

    def machines(self, with_status: bool = True) -> Listing[MachineInfo]:
        """Machines alive on the network (their liveliness tokens), with state and uptime.

        Discovery settles first, as for the default pick (rider/discovery.py): a listing taken
        right after the session opened missed machines that gossip had not linked yet. Where it
        could not settle, or part of the network was out of sight, the listing says so
        (`complete` False, `note` why). One query of `<prefix>/*/status` fills in every state;
        a machine alive but silent within the timeout is listed with `state=None`. Discovery
        declares and undeclares a liveliness subscriber on `<prefix>/*/alive`: zenoh 1.10 (client
        mode) then stops giving new tokens to a `follow_machines` of this Rider declared before
        it, so list first, then follow (as `rider machines --watch` does).
        """
        seen = self._discover(SETTLE_S)
        found: set[str] = set(seen.alive)
        sessions: dict[str, set[str]] = {}
        prefix = f"{self.key_prefix}/"
        # Two queries, not `<prefix>/**`: an ACL profile allows these keys, not everything.
        for pattern in (f"{prefix}*/alive", f"{prefix}*/holder/*"):
            for reply in self.session.liveliness().get(pattern, timeout=self.timeout):
                if reply.ok is not None:
                    mid, _, rest = str(reply.ok.key_expr)[len(prefix) :].partition("/")
                    if rest == "alive":
                        found.add(mid)
                    elif rest.startswith("holder/"):
                        sessions.setdefault(mid, set()).add(rest[len("holder/") :])
        statuses: dict[str, Status] = {}
        if with_status:
            for reply in self._get(f"{prefix}*/status", None, None):
                if reply.ok is None:
                    continue
                try:
                    status = self._decode(reply, Status)
                except RiderError:
                    continue  # one bad reply must not hide the other machines
                mid = str(reply.ok.key_expr).split("/")[-2]
                statuses[mid] = status
                if reply.replier_id is not None:
                    sessions.setdefault(mid, set()).add(str(reply.replier_id.zid))
        out: Listing[MachineInfo] = Listing(complete=seen.sure, note=seen.unsure())
        # One that answers is alive too: a liveliness query racing a history subscription of
        # this session (`follow_machines`) can come back short.
        for mid in sorted(found | statuses.keys()):
            st = statuses.get(mid)
            out.append(
                MachineInfo(
                    id=mid,
                    state=st.state if st else None,
                    uptime_s=st.uptime_s if st else None,
                    sessions=tuple(sorted(sessions.get(mid, ()))),
                )
            )
        return out

    def follow_machines(
        self, timeout: float = 0.5, *, history: bool = True
    ) -> Iterator[tuple[str, bool] | None]:
        """(id, alive) as machines' liveliness tokens come and go; None after each quiet
        `timeout`, so the caller can check its own deadline. Runs until the caller stops.

        `history` first yields every machine alive now. The subscription starts at this call,
        not at the first `next()`: a `machines()` taken after it cannot miss a departure (use
        `history=False` then; a liveliness query racing a history replay comes back short).
        """
        q: queue.Queue[tuple[str, bool]] = queue.Queue()

        def on_token(sample: zenoh.Sample) -> None:
            parts = str(sample.key_expr).split("/")
            q.put((parts[-2], sample.kind == zenoh.SampleKind.PUT))

        sub = self.session.liveliness().declare_subscriber(
            f"{self.key_prefix}/*/alive", _direct(on_token), history=history
        )
        return _drain_changes(q, sub, timeout)

    # ------------------------------------------------------------------------------ watch
    def watch(
        self,
        keys: Iterable[str] = ("status", "io/**", "axis/**"),
        *,
        timeout: float | None = None,
        capacity: int = 4096,
    ) -> Iterator[Update]:
        """Status / IO / axis (and, if asked for, `diag/cycle`) updates as published, newest last.

        Starts with the current status, so a late joiner is never blank. Stops after `timeout`
        seconds without any update (None = never).
        """
        q: queue.Queue[zenoh.Sample] = queue.Queue(maxsize=capacity)

        def on_sample(sample: zenoh.Sample) -> None:
            # A slow reader drops updates rather than stall Zenoh's thread.
            with contextlib.suppress(queue.Full):
                q.put_nowait(sample)

        with self._declare(keys, on_sample):
            if any(k == "status" for k in keys):
                yield self.status()
            while True:
                try:
                    sample = q.get(timeout=timeout)
                except queue.Empty:
                    return
                try:
                    update = _decode_update(sample)
                except BadReply:
                    continue
                if update is not None:
                    yield update

    def subscribe(
        self,
        keys: Iterable[str],
        on_update: Callable[[Update], None],
        on_presence: Callable[[bool], None] | None = None,
    ) -> Subscription:
        """Call `on_update` with each decoded publication on `keys` (under this machine, e.g.
        `status`, `io/**`, `diag/cycle`) and `on_presence` with the machine's liveliness
        (True at once if it is alive now). Both run on Zenoh's network thread, in the order the
        machine published (a status before the notice that follows it): hand off, never block.
        """

        def on_sample(sample: zenoh.Sample) -> None:
            try:
                update = _decode_update(sample)
            except BadReply as exc:
                log.warning("event=bad_sample key=%s error=%r", sample.key_expr, str(exc))
                return
            if update is not None:
                on_update(update)

        def on_token(sample: zenoh.Sample) -> None:
            if on_presence is not None:
                on_presence(sample.kind == zenoh.SampleKind.PUT)

        return self._declare(keys, on_sample, on_token if on_presence is not None else None)

    def _declare(
        self,
        keys: Iterable[str],
        on_sample: Callable[[zenoh.Sample], None],
        on_token: Callable[[zenoh.Sample], None] | None = None,
    ) -> Subscription:
        """Subscribers on `keys` under this machine (and on its `alive` token, with history);
        all or nothing."""
        base, session = self.base, self.session
        entities: list[Any] = []
        known = self.holders(self.machine_id)

        def on_member(sample: zenoh.Sample) -> None:
            kind, _, zid = str(sample.key_expr)[len(base) + 1 :].partition("/")
            known.update(kind, zid, sample.kind == zenoh.SampleKind.PUT)

        def guarded(sample: zenoh.Sample) -> None:
            if self._sample_ok(sample):
                on_sample(sample)
            else:
                suppressed = self._foreign.allow()
                if suppressed is not None:
                    log.warning(
                        "event=foreign_sample key=%s source=%s suppressed=%d",
                        sample.key_expr,
                        _src(sample),
                        suppressed,
                    )

        try:
            with _bus_errors(f"cannot subscribe under {base}"):
                for kind in ("holder", "supervisor"):
                    entities.append(
                        session.liveliness().declare_subscriber(
                            f"{base}/{kind}/*", _direct(on_member), history=True
                        )
                    )
                for key in keys:
                    entities.append(session.declare_subscriber(f"{base}/{key}", _direct(guarded)))
                if on_token is not None:
                    entities.append(
                        session.liveliness().declare_subscriber(
                            f"{base}/alive", _direct(on_token), history=True
                        )
                    )
        except BusError:
            Subscription(entities).close()
            raise
        return Subscription(entities)

    def done(self, transaction: str | Reply, timeout: float | None = None) -> Completion | None:
        """How the motion `transaction` (an id, or its command's reply) ended; None while it
        is still under way. Raises `UnknownTransaction` if the machine knows no such motion."""
        tid = transaction.transaction_id if isinstance(transaction, Reply) else transaction
        if not tid:
            raise UnknownTransaction("a reply without a transaction id has no notice")
        try:
            return self._get_one(f"{self.base}/done/{tid}", None, Completion, timeout)
        except CommandRefused as exc:
            if exc.error.code is ErrorCode.IN_PROGRESS:
                return None
            if exc.error.code is ErrorCode.UNKNOWN_TRANSACTION:
                raise UnknownTransaction(str(exc)) from exc
            raise

    def recent_completions(self) -> list[Completion]:
        """Every completion notice the machine remembers (`done/**`), oldest first."""
        notices = self._get_all(f"{self.base}/done/**", Completion, required=False)
        return sorted(notices, key=lambda n: n.time)

    def wait_done(
        self,
        transaction: str | Reply,
        timeout: float = 600.0,
        *,
        on_status: Callable[[Status], None] | None = None,
        on_silence: Callable[[float], None] | None = None,
        quiet_s: float = 3.0,
        link_limit: float | None = None,
    ) -> Completion:
        """Block until the completion notice of `transaction` (an id, or the reply of the
        command that started it) and return it, whatever its outcome (DONE, STOPPED, FAULT_*…).

        Subscribes to `done/<id>` first, then asks (a notice published before the subscription
        is found), and asks again every `DONE_RECHECK_S` (a dropped publication, a machine that
        restarted and forgot the motion: `UnknownTransaction`). `on_status` gets every status
        meanwhile (e.g. to say the motion is paused or E-stopped); `on_silence` hears, once
        per silence, that no status came for `quiet_s` seconds (a frozen machine, a link down:
        the wait goes on, the operator is told); `LinkLost` once no status came for
        `link_limit` seconds (with `on_status`). MachineTimeout after `timeout` seconds.
        """
        tid = transaction.transaction_id if isinstance(transaction, Reply) else transaction
        if not tid:
            raise UnknownTransaction("a reply without a transaction id has no notice")
        q: queue.Queue[Update] = queue.Queue()
        keys = [f"done/{tid}"] + (["status"] if on_status is not None else [])
        deadline = time.monotonic() + timeout

        def on_sample(sample: zenoh.Sample) -> None:
            with contextlib.suppress(BadReply):
                update = _decode_update(sample)
                if update is not None:
                    q.put(update)

        limit = link_limit if on_status is not None else None
        silence = Silence(quiet_s, on_silence, limit, time.monotonic())
        with self._declare(keys, on_sample):
            recheck = 0.0
            while True:
                now = time.monotonic()
                if (lost := silence.check(now)) is not None:
                    raise LinkLost(
                        f"no word from machine {self.machine_id} for {lost:.0f} s"
                        f" (--link-limit {link_limit:g}); {tid} not known to have ended"
                    )
                if now >= recheck:
                    recheck = now + DONE_RECHECK_S
                    with contextlib.suppress(MachineTimeout):  # down for now: keep waiting
                        notice = self.done(tid)
                        if notice is not None:
                            return notice
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise MachineTimeout(f"no completion notice for {tid} within {timeout:g} s")
                try:
                    update = q.get(timeout=min(remaining, max(recheck - time.monotonic(), 0)))
                except queue.Empty:
                    continue
                if isinstance(update, Completion) and update.transaction_id == tid:
                    return update
                if isinstance(update, Status) and on_status is not None:
                    silence.heard(time.monotonic())
                    on_status(update)

    def wait_for(
        self, states: Iterable[MachineState], timeout: float = 60.0, *, after: float = 0.0
    ) -> Status:
        """Block until the machine is in one of `states`; raise MachineTimeout otherwise.

        Statuses stamped before `after` (e.g. a command reply's timecode) are ignored, so a
        status published before the command took effect never ends the wait early.
        """
        wanted = set(states)
        deadline = time.monotonic() + timeout
        for update in self.watch(("status",), timeout=min(1.5, timeout)):
            if isinstance(update, Status) and update.time >= after and update.state in wanted:
                return update
            if time.monotonic() > deadline:
                break
        last = self.status()  # the watch went quiet: ask once before giving up
        if last.state in wanted and last.time >= after:
            return last
        raise MachineTimeout(f"machine still {last.state} after {timeout:g} s")

    # ---------------------------------------------------------------------------- plumbing
    def _get_one(self, key: str, payload: bytes | None, model: type[M], timeout: float | None) -> M:
        """The first reply. An empty answer that comes back early means no queryable was
        matched yet (a peer's declarations still on their way just after open): ask again
        until the timeout. Safe for commands too: the transaction id makes them at-most-once."""
        limit = timeout or self.timeout
        deadline = time.monotonic() + limit
        while True:
            remaining = deadline - time.monotonic()
            replies = self._get(key, payload, max(remaining, 0.05))
            if len(replies) == 1:  # the usual answer: one reply, from the machine, ok
                sample = replies[0].ok
                if sample is not None:
                    return self._decode_ok(sample, model)
            replies = self._answered(key, replies, limit)
            if replies:
                return self._decode(replies[0], model)
            if deadline - time.monotonic() < EMPTY_RETRY_S:
                hint = self.no_link_hint() or " (is the machine up?)"
                raise MachineTimeout(f"no reply from {key} within {limit:g} s{hint}")
            time.sleep(EMPTY_RETRY_S)

    def _get_all(self, key: str, model: type[M], *, required: bool = True) -> list[M]:
        """Every reply to a wildcard key. `required`: a live machine always answers it (IO,
        axes, parameters), so no reply at all is `MachineTimeout`, never an empty list."""
        replies = self._answered(key, self._get(key, None, None), self.timeout)
        if required and not replies:
            hint = self.no_link_hint() or " (is the machine up?)"
            raise MachineTimeout(f"no reply from {key} within {self.timeout:g} s{hint}")
        return [self._decode(r, model) for r in replies]

    @staticmethod
    def _answered(key: str, replies: list[zenoh.Reply], limit: float) -> list[zenoh.Reply]:
        """The replies a queryable sent. A query that reached one (a frozen or stalled daemon,
        a router forwarding to it) but got no answer in time ends with Zenoh's own error reply
        `Timeout`: that is no reply, never the machine's refusal."""
        answered = [r for r in replies if not _zenoh_timeout(r)]
        if replies and not answered:
            raise MachineTimeout(
                f"no reply from {key} within {limit:g} s: the machine was reached but did not"
                " answer (frozen or overloaded?)"
            )
        return answered

    def _get(self, key: str, payload: bytes | None, timeout: float | None) -> list[zenoh.Reply]:
        """All replies to `key` (asked by its key expression when it is declared)."""
        session = self.session
        target = self._keys.get(key, key)
        # Every reply, not one per key (`_ALL`): two daemons with one id must both be seen.
        # No `_bus_errors` wrapper here: a generator context manager per query costs more
        # than the rest of this function (BENCHMARKS.md, section 1).
        try:
            if payload is None:
                handler = session.get(target, timeout=timeout or self.timeout, consolidation=_ALL)
            else:
                handler = session.get(
                    target,
                    payload=payload,
                    encoding=_MSGPACK,
                    attachment=self._attachment,
                    timeout=timeout or self.timeout,
                    consolidation=_ALL,
                )
            replies = list(handler)
        except zenoh.ZError as exc:
            raise _bus_error(f"cannot query {key}", exc) from exc
        return self._check_repliers(key, replies)

    # ----------------------------------------------------------------------------- pinning
    def _machine_in(self, key: str) -> str | None:
        """The one machine id `key` is under (None: a wildcard id, or not a machine key)."""
        try:
            return self._machine_of[key]
        except KeyError:
            pass
        prefix = f"{self.key_prefix}/"
        mid: str | None = None
        if key.startswith(prefix):
            mid = key[len(prefix) :].split("/", 1)[0]
            if any(c in mid for c in "*$"):
                mid = None
        if len(self._machine_of) >= KEY_CACHE:
            self._machine_of.clear()
        self._machine_of[key] = mid
        return mid

    def holders(self, machine_id: str) -> _Holders:
        """Ask who holds `machine_id` now (its `holder/<zid>` and `supervisor/<zid>` tokens)."""
        known = self._holders.setdefault(machine_id, _Holders())
        seen: dict[str, set[str]] = {"holder": set(), "supervisor": set()}
        base = f"{self.key_prefix}/{machine_id}"
        with _bus_errors(f"cannot query the liveliness of {base}"):
            # One key per kind, not `*/*`: the ACL profiles allow exactly these.
            for kind, group in seen.items():
                for reply in self.session.liveliness().get(
                    f"{base}/{kind}/*", timeout=self.timeout
                ):
                    if reply.ok is not None:
                        group.add(str(reply.ok.key_expr).rsplit("/", 1)[-1])
        for kind, group in (("holder", known.holders), ("supervisor", known.supervisors)):
            for zid in group - seen[kind]:
                known.update(kind, zid, False)
            for zid in seen[kind]:
                known.update(kind, zid, True)
        return known

    def _check_repliers(self, key: str, replies: list[zenoh.Reply]) -> list[zenoh.Reply]:
        """One session answers for one machine, and it is the pinned one (or its supervisor);
        the replies to use (the daemon's, when its supervisor answered beside it)."""
        mid = self._machine_in(key)
        if mid is None:
            return replies
        if len(replies) == 1:  # a command's usual answer: one reply, one replier
            replier = replies[0].replier_id
            if replier is None:
                return replies
            replier_id = replier.zid
            known = self._holders.get(mid)
            if (
                known is not None
                and known.allowed_at == known.changes
                and known.allowed == replier_id
            ):
                return replies  # the replier allowed last time, and nothing changed since
            self._vet(mid, key, str(replier_id), replier_id)
            return replies
        repliers = sorted({str(r.replier_id.zid) for r in replies if r.replier_id is not None})
        if len(repliers) > 1:
            replies, repliers = self._without_stand_in(mid, replies, repliers)
        if len(repliers) > 1:
            raise DuplicateMachine(mid, repliers, f"{len(repliers)} sessions replied to {key}")
        if repliers:
            self._vet(mid, key, repliers[0], None)
        return replies

    def _without_stand_in(
        self, mid: str, replies: list[zenoh.Reply], repliers: list[str]
    ) -> tuple[list[zenoh.Reply], list[str]]:
        """A supervisor answers for its machine while the daemon is down, and for a moment
        after a restarted daemon answers again (until it has seen the daemon's token): its
        reply is dropped when another session replied beside it."""
        supervisors = self.holders(mid).supervisors
        others = [z for z in repliers if z not in supervisors]
        if not others or len(others) == len(repliers):
            return replies, repliers
        kept = [r for r in replies if r.replier_id is None or str(r.replier_id.zid) in others]
        return kept, others

    def _vet(self, mid: str, key: str, zid: str, replier_id: zenoh.ZenohId | None) -> None:
        """`zid`, the one session that replied to `key`, may answer for machine `mid`
        (`DuplicateMachine` otherwise); remembered by its `zenoh.ZenohId` when given."""
        known = self._holders.get(mid)
        if known is None or not known.allows(zid):
            known = self.holders(mid)  # first contact, or the holder changed since
        checked = known.changes
        if len(known.holders) > 1:
            raise DuplicateMachine(mid, sorted(known.holders), "each holds the machine's token")
        if known.pinned is None and not known.holders:
            known.pinned = zid  # a daemon that names no holder: its first reply pins it
        if not known.allows(zid):
            raise DuplicateMachine(
                mid,
                [str(known.pinned), zid],
                f"{zid} replied to {key}, but this Rider talks to {known.pinned}",
            )
        if replier_id is not None:
            known.allowed, known.allowed_at = replier_id, checked

    def _sample_ok(self, sample: zenoh.Sample) -> bool:
        """A publication under a machine from the pinned session (or its supervisor); one
        that names no source is not the machine's own (every machine publication names it)."""
        key = str(sample.key_expr)
        mid = self._machine_in(key)
        known = self._holders.get(mid) if mid is not None else None
        if known is None or known.pinned is None:
            return True  # no contact yet: nothing to compare with
        source = sample.source_info
        if source is None:
            return False
        return known.allows(str(source.source_id.zid))

    @staticmethod
    def _decode(reply: zenoh.Reply, model: type[M]) -> M:
        sample = reply.ok
        if sample is None:
            err = reply.err
            data = err.payload.to_bytes() if err is not None else b""
            fmt = _format_of(err.encoding if err is not None else None)
            try:
                refused = decode(Reply, data, fmt)
            except DecodeError as exc:
                raise BadReply(f"error reply: {data[:200]!r}") from exc
            raise CommandRefused(refused)
        return Rider._decode_ok(sample, model)

    @staticmethod
    def _decode_ok(sample: zenoh.Sample, model: type[M]) -> M:
        """A reply's sample as `model`; `BadReply` (or `CommandRefused` for an error `Reply`)
        when it is none (`_read`, else the long way, which says why)."""
        data = sample.payload.to_bytes()
        encoding = sample.encoding
        result = _read(data, encoding, model, MAX_REPLY_BYTES)
        if result is not None:
            return result
        fmt = _format_of(encoding)
        try:
            return decode(model, data, fmt, MAX_REPLY_BYTES)
        except DecodeError as exc:
            # An error reply on a key that normally carries `model` (e.g. unknown parameter).
            try:
                refused = decode(Reply, data, fmt)
            except DecodeError:
                raise BadReply(f"{sample.key_expr}: {exc.error.message}") from exc
            if refused.success:
                raise BadReply(f"{sample.key_expr}: {exc.error.message}") from exc
            raise CommandRefused(refused) from exc
        except ValidationError as exc:  # pragma: no cover - decode wraps these
            raise BadReply(str(exc)) from exc


def _direct(callback: Callable[[zenoh.Sample], None]) -> zenoh.handlers.Callback[zenoh.Sample]:
    """Run `callback` on Zenoh's network thread. zenoh-python's default runs each subscriber's
    callback on a thread of its own, so samples of two subscribers (e.g. `status` and `done/*`)
    reach the caller out of the order the machine published them in (~20 % under load). The
    thread keeps its Python state between samples (`schema.threadstate`)."""
    return zenoh.handlers.Callback(keeping_state(callback), indirect=False)


FOREIGN_LOG_EVERY_S = 10.0
"""A `foreign_sample` warning at most this often (the first at once)."""


class Throttle:
    """A line that may repeat at any rate: the first passes, then at most one per `every_s`,
    saying how many were held back since the last (thread-safe: Zenoh's threads call it)."""

    def __init__(self, every_s: float, clock: Callable[[], float] = time.monotonic) -> None:
        self.every_s = every_s
        self.clock = clock
        self._lock = threading.Lock()
        self._next = -math.inf
        self._held = 0

    def allow(self) -> int | None:
        """None: hold this one back (counted); else how many were held back before it."""
        with self._lock:
            now = self.clock()
            if now < self._next:
                self._held += 1
                return None
            held, self._held = self._held, 0
            self._next = now + self.every_s
            return held


KEY_CACHE = 256
"""Keys whose machine id a Rider remembers (the same few keys are asked again and again)."""


def _zenoh_timeout(reply: zenoh.Reply) -> bool:
    """Zenoh's own end of a query nobody answered in time (not a reply from a machine)."""
    return reply.ok is None and reply.err is not None and reply.err.payload.to_bytes() == b"Timeout"


def _src(sample: zenoh.Sample) -> str:
    source = sample.source_info
    return "none" if source is None else str(source.source_id.zid)


def _read(data: bytes, encoding: zenoh.Encoding, model: type[M], limit: int) -> M | None:
    """`data` as `model` in one unpack and one validation by the model's validator (what
    `model_validate` calls, without its wrapper): the usual msgpack payload, at two thirds of
    `decode`'s cost run hot. None for anything else (another encoding, too large, not a map,
    invalid): the caller decodes that with `decode`, which says why (BENCHMARKS.md, section 9)."""
    if encoding == _MSGPACK and len(data) <= limit:
        try:
            raw = msgpack.unpackb(data, raw=False, strict_map_key=True)
            if type(raw) is dict:
                result: M = model.__pydantic_validator__.validate_python(raw)
                return result
        except (ValueError, RecursionError, msgpack.UnpackException, ValidationError):
            pass
    return None


def _decode_sample(sample: zenoh.Sample, model: type[M], limit: int) -> M:
    """A published sample as `model` (`_read`, else `decode`, which says why); `BadReply`
    naming its key when it is none."""
    data = sample.payload.to_bytes()
    encoding = sample.encoding
    result = _read(data, encoding, model, limit)
    if result is not None:
        return result
    try:
        return decode(model, data, _format_of(encoding), limit)
    except DecodeError as exc:
        raise BadReply(f"{sample.key_expr}: {exc.error.message}") from exc


def _format_of(encoding: zenoh.Encoding | None) -> Format:
    return Format.JSON if str(encoding or "").startswith(Format.JSON) else Format.MSGPACK


def _decode_update(sample: zenoh.Sample) -> Update | None:
    """A published sample as its wire model; None for a key that carries none of them.

    Raises `BadReply` for data that does not decode as the key's model."""
    key = str(sample.key_expr)
    model: type[BaseModel]
    if key.endswith("/status"):
        model = Status
    elif "/io/" in key:
        model = IoValue
    elif "/axis/" in key:
        model = AxisRecord
    elif key.endswith("/diag/cycle"):
        model = CycleDiag
    elif "/done/" in key:
        model = Completion
    elif key.endswith("/calibration"):
        model = CalibrationRecord
    else:
        return None
    result = _decode_sample(sample, model, MAX_PAYLOAD_BYTES)
    assert isinstance(
        result, Status | IoValue | AxisRecord | CycleDiag | Completion | CalibrationRecord
    )
    return result


@contextlib.contextmanager
def _bus_errors(what: str) -> Iterator[None]:
    """Zenoh's own error (a closed or broken session, a bad key) as a `BusError`."""
    try:
        yield
    except zenoh.ZError as exc:
        raise _bus_error(what, exc) from exc


def _bus_error(what: str, exc: zenoh.ZError) -> BusError:
    where = str(exc).split(" at /", 1)[0]  # not the Rust source path of the check
    return BusError(f"{what}: {where}")


def _drain_changes(
    q: queue.Queue[tuple[str, bool]], sub: Any, timeout: float
) -> Iterator[tuple[str, bool] | None]:
    try:
        while True:
            try:
                yield q.get(timeout=timeout)
            except queue.Empty:
                yield None
    finally:
        sub.undeclare()


def _result(reply: Reply) -> CheckResult:
    if reply.result is None:
        raise BadReply(f"{reply.command} reply carries no result")
    return reply.result


class AsyncRider:
    """The same client for asyncio: blocking Zenoh calls run in a worker thread."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self._sync = Rider(*args, **kwargs)

    async def __aenter__(self) -> AsyncRider:
        await asyncio.to_thread(self._sync.open)
        return self

    async def __aexit__(self, *exc: object) -> None:
        await asyncio.to_thread(self._sync.close)

    @property
    def rider_id(self) -> str:
        return self._sync.rider_id

    async def command(self, command: Command, request: CommandRequest | None = None) -> Reply:
        return await asyncio.to_thread(self._sync.command, command, request)

    async def start(self, session: Session | None = None) -> Reply:
        return await asyncio.to_thread(self._sync.start, session)

    async def status(self) -> Status:
        return await asyncio.to_thread(self._sync.status)

    def __getattr__(self, name: str) -> Any:
        target = getattr(self._sync, name)
        if not callable(target):
            return target

        async def call(*args: Any, **kwargs: Any) -> Any:
            return await asyncio.to_thread(target, *args, **kwargs)

        return call

    async def watch(
        self, keys: Iterable[str] = ("status", "io/**", "axis/**"), timeout: float | None = None
    ) -> AsyncIterator[Update]:
        """Updates as an async iterator (a thread feeds an asyncio queue)."""
        loop = asyncio.get_running_loop()
        out: asyncio.Queue[Update | None] = asyncio.Queue()
        stop = threading.Event()

        def deliver(item: Update | None) -> bool:
            """Hand `item` to the loop; False once the consumer or the loop itself is gone."""
            if stop.is_set() or loop.is_closed():
                return False
            try:
                loop.call_soon_threadsafe(out.put_nowait, item)
            except RuntimeError:  # the loop closed between the check and the call
                return False
            return True

        def pump() -> None:
            try:
                for update in self._sync.watch(keys, timeout=timeout):
                    if not deliver(update):
                        break
            finally:
                deliver(None)

        worker = threading.Thread(target=pump, name="rider-watch", daemon=True)
        worker.start()
        try:
            while (item := await out.get()) is not None:
                yield item
        finally:
            stop.set()


def env_connect() -> list[str]:
    """Endpoints from RIDER_CONNECT (comma separated), if set."""
    raw = os.environ.get("RIDER_CONNECT", "")
    return [e.strip() for e in raw.split(",") if e.strip()]
