"""`Rider`, the blocking client: a thin façade over its parts, one method per command, read,
event query, subscription and wait (the parts: rider/client.py's docstring lists them)."""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any, Generic, TypeVar, overload

import zenoh

from ride_machine.schema.axes import AxisRecord
from ride_machine.schema.calibration import (
    CalibrationRecord,
    RotateCalibrationSet,
    TiltCalibrationSet,
)
from ride_machine.schema.commands import (
    CheckResult,
    Command,
    CommandRequest,
    Reply,
    Session,
    StartRequest,
)
from ride_machine.schema.diag import CycleDiag
from ride_machine.schema.findings import Findings
from ride_machine.schema.io import IoValue
from ride_machine.schema.params import ParamValue
from ride_machine.schema.sim import SimWorldState
from ride_machine.schema.status import MachineState, Status

from .commands import Commands
from .discovery import Discovery, Listing, Lookahead
from .link import DEFAULT_TIMEOUT_S, Link
from .machines import MachineInfo, Machines
from .pinning import Holders
from .reads import Reads
from .replies import Update, check_result
from .subscriptions import Subscription, Subscriptions
from .transport import Transport

if TYPE_CHECKING:  # loaded by the first event query or wait: `rider status` needs neither
    from ride_machine.common.event_summary import EventSummary
    from ride_machine.schema.completion import Completion
    from ride_machine.schema.events import Event, EventPage, EventQuery

    from .completions import Completions
    from .events import Events

T = TypeVar("T")


class FromLink(Generic[T]):
    """A `Rider` attribute that is its link's (the session and the options every part reads
    there), read-only: `session`, `rider_id`, `login`, `timeout`, …"""

    def __set_name__(self, owner: type, name: str) -> None:
        self.name = name

    @overload
    def __get__(self, rider: None, kind: type) -> FromLink[T]: ...

    @overload
    def __get__(self, rider: Rider, kind: type | None = None) -> T: ...

    def __get__(self, rider: Rider | None, kind: type | None = None) -> T | FromLink[T]:
        if rider is None:
            return self
        value: T = getattr(rider.link, self.name)
        return value


class Rider:
    """A synchronous Rider session; use as a context manager so the session always closes."""

    session: FromLink[zenoh.Session] = FromLink()
    rider_id: FromLink[str] = FromLink()
    """This Rider's id, `<login>/<zid>` (its keys: `rider/<rider_id>/…`); "" until open."""
    login: FromLink[str] = FromLink()
    """The login this Rider's keys are under (`rider/<login>/<zid>/…`)."""
    key_prefix: FromLink[str] = FromLink()
    timeout: FromLink[float] = FromLink()
    retries: FromLink[int] = FromLink()
    supervise: FromLink[bool] = FromLink()
    zenoh_threads: FromLink[int] = FromLink()

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
        link = Link(
            zenoh_config_path,
            connect,
            listen,
            key_prefix=key_prefix,
            timeout=timeout,
            retries=retries,
            supervise=supervise,
            zenoh_threads=zenoh_threads,
        )
        self._assemble(link, machine_id, None)

    @classmethod
    def on_link(
        cls, link: Link, machine_id: str | None, lookahead: Lookahead | None = None
    ) -> Rider:
        """A Rider on a link made (and perhaps opened) before the client was loaded, with the
        default-machine lookup perhaps already under way (`rider/cli.py` does both, so the
        lookup's settle window runs while the wire models load)."""
        rider = cls.__new__(cls)
        rider._assemble(link, machine_id, lookahead)
        return rider

    def _assemble(self, link: Link, machine_id: str | None, lookahead: Lookahead | None) -> None:
        self.link = link
        self.transport = Transport(self.link)
        self._machines = Machines(self.link, self.transport, machine_id, lookahead)
        self._commands = Commands(self.link, self._machines, self.transport)
        self._reads = Reads(self._machines, self.transport, self._commands)
        self._subs = Subscriptions(self.link, self._machines, self.transport.pins)

    @functools.cached_property
    def _events(self) -> Events:
        """The event history's part, made at its first use (its models are the largest)."""
        from .events import Events

        return Events(self.link, self._machines, self.transport, self._subs)

    @functools.cached_property
    def _completions(self) -> Completions:
        """Completion notices and waits, made at their first use."""
        from .completions import Completions

        return Completions(self._machines, self.transport, self._subs, self._reads)

    # ---------------------------------------------------------------------------- session
    def open(self) -> Rider:
        if not self.link.is_open:
            self.link.open()
        self._commands.check_ids()
        return self

    def close(self) -> None:
        """Stop the heartbeat, undeclare the liveliness token, close the session (always)."""
        self.link.close()
        self._commands.forget_keys()

    def __enter__(self) -> Rider:
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def no_link_hint(self) -> str:
        """Why nothing answers, when this session has no link at all ("" when it has one)."""
        return self.link.no_link_hint()

    # --------------------------------------------------------------------------- machines
    @property
    def machine_id(self) -> str:
        """The machine this Rider talks to: the one named, else the only one alive once
        discovery has settled (`resolve_machine`)."""
        return self._machines.pick()

    @property
    def base(self) -> str:
        return self._machines.base

    def pick_machine(self, *, motion: bool = False) -> str:
        """The machine named, else the default one (looked up once, then kept)."""
        return self._machines.pick(motion=motion)

    def resolve_machine(self, *, motion: bool = False) -> str:
        """The only machine alive, after discovery settled (rider/discovery.py); raises
        `NoMachine`, `AmbiguousMachine` (several), or `UnsureMachine` (never settled).
        `motion` waits longer (`MOTION_SETTLE_S`) before a command may move a ride."""
        return self._machines.resolve(motion=motion)

    @property
    def discovery(self) -> Discovery | None:
        """What the default-machine lookup saw (None when a machine was named)."""
        return self._machines.discovery

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
        return self._machines.listing(with_status)

    def follow_machines(
        self, timeout: float = 0.5, *, history: bool = True
    ) -> Iterator[tuple[str, bool] | None]:
        """(id, alive) as machines' liveliness tokens come and go; None after each quiet
        `timeout`, so the caller can check its own deadline. Runs until the caller stops.

        `history` first yields every machine alive now. The subscription starts at this call,
        not at the first `next()`: a `machines()` taken after it cannot miss a departure (use
        `history=False` then; a liveliness query racing a history replay comes back short).
        """
        return self._machines.follow(timeout, history=history)

    def holders(self, machine_id: str) -> Holders:
        """Ask who holds `machine_id` now (its `holder/<zid>` and `supervisor/<zid>` tokens)."""
        return self.transport.pins.holders(machine_id)

    # --------------------------------------------------------------------------- commands
    def new_transaction_id(self) -> str:
        return self._commands.new_transaction_id()

    def command(
        self,
        command: Command,
        request: CommandRequest | None = None,
        *,
        check: bool = True,
        timeout: float | None = None,
    ) -> Reply:
        """Send one command; raises `CommandRefused` on an error reply when `check`."""
        return self._commands.command(command, request, check=check, timeout=timeout)

    def calibrate_tilt(self) -> Reply:
        return self.command(Command.CALIBRATE_TILT)

    def calibrate_rotate(self) -> Reply:
        return self.command(Command.CALIBRATE_ROTATE)

    def home(self) -> Reply:
        return self.command(Command.HOME)

    def start(self, session: Session | None = None) -> Reply:
        request = StartRequest.model_validate(self._commands.fields(session=session))
        return self.command(Command.START, request)

    def pause(self) -> Reply:
        return self.command(Command.PAUSE)

    def resume(self) -> Reply:
        return self.command(Command.RESUME)

    def stop(self) -> Reply:
        return self.command(Command.STOP)

    def check_calibration(self) -> CheckResult:
        return check_result(self.command(Command.CHECK_CALIBRATION))

    def check_home(self) -> CheckResult:
        return check_result(self.command(Command.CHECK_HOME))

    # ---------------------------------------------------------------------------- reading
    def status(self, timeout: float | None = None) -> Status:
        return self._reads.status(timeout)

    def io(self) -> list[IoValue]:
        return self._reads.io()

    def axes(self) -> list[AxisRecord]:
        return self._reads.axes()

    def diag(self, reset: bool = False) -> CycleDiag:
        """The scan loop's diagnostics; `reset` also clears min/max, overruns and missed
        cycles (a command key, `diag/reset`, so the ACL can keep it from read-only identities)."""
        return self._reads.diag(reset)

    def validate(self, candidate: bytes | None = None) -> Findings:
        """Findings for the running config, or for a candidate TOML/JSON config."""
        return self._reads.validate(candidate)

    def calibration(self) -> CalibrationRecord:
        """The machine's calibration values: how and when each axis got them."""
        return self._reads.calibration()

    def set_calibration(
        self,
        *,
        tilt: TiltCalibrationSet | None = None,
        rotate: RotateCalibrationSet | None = None,
    ) -> CalibrationRecord:
        """Enter calibration values by hand (recorded as manual; refused while moving);
        returns the record once the machine has saved them (`CommandRefused` otherwise)."""
        return self._reads.set_calibration(tilt=tilt, rotate=rotate)

    def params(self) -> list[ParamValue]:
        return self._reads.params()

    def param(self, name: str) -> ParamValue:
        return self._reads.param(name)

    def set_param(self, name: str, value: Any, *, persist: bool = False) -> ParamValue:
        return self._reads.set_param(name, value, persist=persist)

    def reset_param(self, name: str) -> ParamValue:
        return self._reads.reset_param(name)

    def sim(self, /, fault: str, **payload: Any) -> SimWorldState:
        """Inject a simulator fault (estop, home, tilt_ai, stall, clear) or read the `world`."""
        return self._reads.sim(fault, **payload)

    # ----------------------------------------------------------------------------- events
    def event_pages(self, query: EventQuery | None = None) -> list[EventPage]:
        """Every page of the history `query` selects, from this machine, or from every machine
        that answers when the machine id is `*` (each machine's pages in order)."""
        return self._events.pages(query)

    def events(self, /, query: EventQuery | None = None, **criteria: Any) -> list[Event]:
        """The events `query` (or `EventQuery(**criteria)`) selects, oldest first; with the
        machine id `*`, every machine's, ordered by time."""
        return self._events.events(query, **criteria)

    def events_summary(
        self, since_time: float | None = None, until_time: float | None = None
    ) -> list[EventSummary]:
        """Sessions, ride time, E-stops and faults by code over a time range, per machine."""
        return self._events.summary(since_time, until_time)

    def follow_events(
        self, query: EventQuery | None = None, *, timeout: float | None = None
    ) -> Iterator[Event | None]:
        """The history `query` selects, then each new event as it is written; None after each
        quiet `timeout` (None: wait forever), so the caller can check its own deadline.

        The subscription starts before the history is read, so nothing falls in between; a
        gap in a machine's seq numbers (events published while the link was down, e.g. while
        the daemon restarted) is read from its history before the event after it.
        """
        return self._events.follow(query, timeout=timeout)

    # ------------------------------------------------------------------- live publications
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
        return self._subs.watch(keys, self.status, timeout=timeout, capacity=capacity)

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
        return self._subs.subscribe(keys, on_update, on_presence)

    # ------------------------------------------------------------------------ completions
    def done(self, transaction: str | Reply, timeout: float | None = None) -> Completion | None:
        """How the motion `transaction` (an id, or its command's reply) ended; None while it
        is still under way. Raises `UnknownTransaction` if the machine knows no such motion."""
        return self._completions.done(transaction, timeout)

    def recent_completions(self) -> list[Completion]:
        """Every completion notice the machine remembers (`done/**`), oldest first."""
        return self._completions.recent()

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
        return self._completions.wait_done(
            transaction,
            timeout,
            on_status=on_status,
            on_silence=on_silence,
            quiet_s=quiet_s,
            link_limit=link_limit,
        )

    def wait_for(
        self, states: Iterable[MachineState], timeout: float = 60.0, *, after: float = 0.0
    ) -> Status:
        """Block until the machine is in one of `states`; raise MachineTimeout otherwise.

        Statuses stamped before `after` (e.g. a command reply's timecode) are ignored, so a
        status published before the command took effect never ends the wait early.
        """
        return self._completions.wait_for(states, timeout, after=after)
