"""The gateway's Zenoh side: one session, the machines' tokens, each machine's publications and
commands (through the Rider client), and the supervision of each commanding OPC UA session.

Zenoh callbacks never call Zenoh nor block: they hand what arrived to the gateway's event loop
(`Deliver`). Declarations and queries run on worker threads, never on the loop.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import zenoh

from ride_machine.rider.client import (
    Heartbeat,
    MachineTimeout,
    Rider,
    RiderError,
    Subscription,
    Update,
    open_session,
    zenoh_config,
)
from ride_machine.rider.confirm import Confirmations, Ledger
from ride_machine.schema.axes import AxisRecord
from ride_machine.schema.codec import MAX_PAYLOAD_BYTES, DecodeError, Format, decode
from ride_machine.schema.commands import Command, CommandRequest, Reply
from ride_machine.schema.diag import CycleDiag
from ride_machine.schema.events import Event
from ride_machine.schema.io import IoValue
from ride_machine.schema.rider import alive_key
from ride_machine.schema.status import Status

log = logging.getLogger(__name__)

Deliver = Callable[[str, Any], None]
"""(machine id, what arrived): a `bool` for presence, an `Update`, a `Snapshot`, an `Event`."""


@dataclass(frozen=True)
class Snapshot:
    """A value the gateway read on request (at attach, or when a machine's token came back),
    not a publication: it fills a value nobody published since, never replaces one."""

    update: Status | CycleDiag | IoValue | AxisRecord


KEYS = ("status", "io/**", "axis/**", "diag/cycle")
"""The publications the gateway follows under each machine."""


class MachineLink(Rider):
    """A Rider for one machine on the gateway's own session: the client's command path, its
    replies and its pinning of the one session that holds the machine's id, without a session
    (or a heartbeat) of its own. Each OPC UA session supervises under its own Rider id.
    `close` undeclares this machine's keys; the session is the gateway's."""

    def __init__(self, session: zenoh.Session, machine_id: str, *, prefix: str, timeout: float):
        super().__init__(machine_id, key_prefix=prefix, timeout=timeout, supervise=False)
        self.link.borrow(session)


@dataclass
class Attached:
    """A machine the gateway follows: its link and its subscriptions."""

    machine_id: str
    link: MachineLink
    subscriptions: list[Any]

    def close(self) -> None:
        for sub in self.subscriptions:
            if isinstance(sub, Subscription):
                sub.close()
            else:
                with contextlib.suppress(zenoh.ZError):
                    sub.undeclare()
        self.link.close()


@dataclass
class Supervision:
    """One OPC UA session's presence as a Rider: its liveliness token and its heartbeat."""

    token: Any
    heartbeat: Heartbeat
    confirmations: Confirmations

    def close(self) -> None:
        self.confirmations.close()
        self.heartbeat.close()
        with contextlib.suppress(zenoh.ZError):
            self.token.undeclare()


class GatewayBus:
    """The gateway's Zenoh session (as a Rider opens one: `RIDER_ZENOH_*` credentials)."""

    def __init__(
        self,
        connect: list[str],
        zenoh_config_path: Path | None,
        *,
        prefix: str = "machine",
        timeout: float = 2.0,
        zenoh_threads: int = 1,
    ) -> None:
        self.prefix = prefix
        self.timeout = timeout
        try:
            self._session = open_session(zenoh_config(zenoh_config_path, connect), zenoh_threads)
        except zenoh.ZError as exc:
            raise MachineTimeout(f"cannot open the Zenoh session: {exc}") from exc
        self._presence: Any = None
        self.ledger = Ledger()
        """Every request the gateway sent, to any machine: its operator sessions' Riders
        confirm them when a machine asks (rider/confirm.py)."""

    @property
    def zid(self) -> str:
        return str(self._session.zid())

    def follow(self, deliver: Deliver) -> None:
        """Machines arriving and leaving (their `alive` tokens, those alive now first)."""

        def on_token(sample: zenoh.Sample) -> None:
            machine_id = str(sample.key_expr).split("/")[-2]
            deliver(machine_id, sample.kind == zenoh.SampleKind.PUT)

        self._presence = self._session.liveliness().declare_subscriber(
            f"{self.prefix}/*/alive", on_token, history=True
        )

    def attach(self, machine_id: str, deliver: Deliver) -> Attached:
        """Follow one machine: its publications and events, then its current values (so a
        machine that is at rest is not blank). Blocking: run it on a worker thread."""
        link = MachineLink(self._session, machine_id, prefix=self.prefix, timeout=self.timeout)
        link.link.ledger = self.ledger

        def on_update(update: Update) -> None:
            deliver(machine_id, update)

        def on_event(sample: zenoh.Sample) -> None:
            json = str(sample.encoding).startswith(Format.JSON)
            try:
                event = decode(
                    Event,
                    sample.payload.to_bytes(),
                    Format.JSON if json else Format.MSGPACK,
                    MAX_PAYLOAD_BYTES,
                )
            except DecodeError as exc:
                log.warning(
                    "event=bad_event key=%r error=%r", str(sample.key_expr), exc.error.message
                )
                return
            deliver(machine_id, event)

        subs: list[Any] = [link.subscribe(KEYS, on_update)]
        attached = Attached(machine_id, link, subs)
        try:
            base = f"{self.prefix}/{machine_id}"
            subs.append(self._session.declare_subscriber(f"{base}/events/*", on_event))
            self.refresh(attached, deliver)
        except BaseException:
            attached.close()
            raise
        return attached

    def refresh(self, attached: Attached, deliver: Deliver) -> None:
        """Read the machine's current values and hand them over as `Snapshot`s: after a
        drop-out (its token went and came back) values published only on change, IO and
        axes at rest, would otherwise stay Bad. Blocking: run it on a worker thread."""
        for current in _current_values(attached.link):
            deliver(attached.machine_id, Snapshot(current))

    def command(
        self, attached: Attached, command: Command, request: CommandRequest, timeout: float
    ) -> Reply:
        """The Rider client's command path (a retry keeps the transaction id); the reply as the
        machine gave it, refused or not. Blocking: run it on a worker thread."""
        return attached.link.command(command, request, check=False, timeout=timeout)

    def supervise(self, rider_id: str, operator: str | None = None) -> Supervision:
        """Hold `rider/<rider_id>/alive`, beat `rider/<rider_id>/heartbeat` and confirm the
        gateway's requests on `rider/<rider_id>/confirm` until closed, naming `operator` (the
        OPC UA user) in each confirmation: the machine records who commanded."""
        session = self._session
        confirmations = Confirmations(session, rider_id, self.ledger, operator)
        token = session.liveliness().declare_token(alive_key(rider_id))
        return Supervision(token, Heartbeat(session, rider_id), confirmations)

    def close(self) -> None:
        if self._presence is not None:
            with contextlib.suppress(zenoh.ZError):
                self._presence.undeclare()
        self._session.close()  # type: ignore[no-untyped-call]


def _current_values(link: MachineLink) -> list[Any]:
    """What the machine answers now: status, diagnostics, IO and axes (each may time out: the
    publications fill in what a read missed)."""
    out: list[Any] = []
    for read in (link.status, link.diag, link.io, link.axes):
        try:
            got = read()
        except RiderError as exc:  # e.g. a machine leaving: the publications fill in or not
            log.info("event=initial_read_missed machine=%s error=%r", link.base, str(exc))
            continue
        out.extend(got if isinstance(got, list) else [got])
    return out
