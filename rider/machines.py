"""Which machine a Rider talks to (the one named, else the only one alive once discovery has
settled: rider/discovery.py), and the machines alive on the network as they come and go."""

from __future__ import annotations

import queue
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import zenoh

from ride_machine.schema.status import MachineState, Status

from .discovery import MOTION_SETTLE_S, SETTLE_S, Discovery, Listing, Lookahead
from .errors import AmbiguousMachine, NoMachine, RiderError, UnsureMachine
from .link import Link, direct
from .replies import decode_reply
from .transport import Transport


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


class Machines:
    """The machine this Rider talks to, and the others alive on the network."""

    def __init__(
        self,
        link: Link,
        transport: Transport,
        machine_id: str | None,
        lookahead: Lookahead | None = None,
    ) -> None:
        """`lookahead`: a lookup begun before this Rider was made (rider/cli.py), taken by the
        first lookup that asks for no longer a settle than it waited for."""
        self.link = link
        self.transport = transport
        self._machine_id = machine_id
        self._lookahead = lookahead
        self.discovery: Discovery | None = None
        """What the default-machine lookup saw (None when a machine was named)."""

    @property
    def base(self) -> str:
        return f"{self.link.key_prefix}/{self.pick()}"

    def pick(self, *, motion: bool = False) -> str:
        """The machine named, else the default one (looked up once, then kept)."""
        if self._machine_id is None:
            self._machine_id = self.resolve(motion=motion)
        return self._machine_id

    def resolve(self, *, motion: bool = False) -> str:
        """The only machine alive, after discovery settled (rider/discovery.py); raises
        `NoMachine`, `AmbiguousMachine` (several), or `UnsureMachine` (never settled).
        `motion` waits longer (`MOTION_SETTLE_S`) before a command may move a ride."""
        seen = self.discover(MOTION_SETTLE_S if motion else SETTLE_S)
        if not seen.links:
            raise NoMachine(f"no machine is alive on the network{self.link.no_link_hint()}")
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
            raise NoMachine(f"no machine is alive on the network{self.link.no_link_hint()}")
        if len(seen.alive) > 1:
            ids = ", ".join(sorted(seen.alive))
            raise AmbiguousMachine(f"several machines are alive ({ids}); pass --machine ID")
        return next(iter(seen.alive))

    def discover(self, settle: float) -> Discovery:
        """Discovery, settled (rider/discovery.py), kept as `self.discovery`. A lookahead is
        waited for first (one lookup at a time on a session) and taken when it waited for at
        least `settle`."""
        early, self._lookahead = self._lookahead, None
        if early is not None:
            seen = early.result()
            if early.settle >= settle:
                self.discovery = seen
                return seen
        self.discovery = self.link.lookup(settle)
        return self.discovery

    def listing(self, with_status: bool = True) -> Listing[MachineInfo]:
        """Machines alive on the network (their liveliness tokens), with state and uptime
        (`Rider.machines` says how the listing is taken)."""
        seen = self.discover(SETTLE_S)
        found, sessions = self._tokens()
        found |= seen.alive
        statuses = self._statuses(sessions) if with_status else {}
        out: Listing[MachineInfo] = Listing(complete=seen.sure, note=seen.unsure())
        # One that answers is alive too: a liveliness query racing a history subscription of
        # this session (`follow`) can come back short.
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

    def _tokens(self) -> tuple[set[str], dict[str, set[str]]]:
        """The machine ids whose `alive` token answers, and the sessions holding each one."""
        found: set[str] = set()
        sessions: dict[str, set[str]] = {}
        prefix = f"{self.link.key_prefix}/"
        # Two queries, not `<prefix>/**`: an ACL profile allows these keys, not everything.
        for pattern in (f"{prefix}*/alive", f"{prefix}*/holder/*"):
            for reply in self.link.session.liveliness().get(pattern, timeout=self.link.timeout):
                if reply.ok is not None:
                    mid, _, rest = str(reply.ok.key_expr)[len(prefix) :].partition("/")
                    if rest == "alive":
                        found.add(mid)
                    elif rest.startswith("holder/"):
                        sessions.setdefault(mid, set()).add(rest[len("holder/") :])
        return found, sessions

    def _statuses(self, sessions: dict[str, set[str]]) -> dict[str, Status]:
        """Every machine's status from one query of `<prefix>/*/status` (its repliers added to
        `sessions`); a machine alive but silent within the timeout has none."""
        statuses: dict[str, Status] = {}
        for reply in self.transport.get(f"{self.link.key_prefix}/*/status", None, None):
            if reply.ok is None:
                continue
            try:
                status = decode_reply(reply, Status)
            except RiderError:
                continue  # one bad reply must not hide the other machines
            mid = str(reply.ok.key_expr).split("/")[-2]
            statuses[mid] = status
            if reply.replier_id is not None:
                sessions.setdefault(mid, set()).add(str(reply.replier_id.zid))
        return statuses

    def follow(self, timeout: float, *, history: bool) -> Iterator[tuple[str, bool] | None]:
        """(id, alive) as machines' liveliness tokens come and go; None after each quiet
        `timeout` (`Rider.follow_machines`). The subscription starts at this call."""
        q: queue.Queue[tuple[str, bool]] = queue.Queue()

        def on_token(sample: zenoh.Sample) -> None:
            parts = str(sample.key_expr).split("/")
            q.put((parts[-2], sample.kind == zenoh.SampleKind.PUT))

        sub = self.link.session.liveliness().declare_subscriber(
            f"{self.link.key_prefix}/*/alive", direct(on_token), history=history
        )
        return _drain_changes(q, sub, timeout)


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
