"""Ordering under a concurrent command storm: commands run in Zenoh callbacks between scan cycles,
so several Riders at once must still see E-stop handled first and one reply per transaction."""

from __future__ import annotations

import contextlib
import itertools
import threading
import time
from collections import Counter
from pathlib import Path

import pytest

from ride_machine.rider.client import Rider
from ride_machine.schema.codec import Format, decode, pack
from ride_machine.schema.commands import Command, Reply
from ride_machine.schema.events import CommandEvent, EstopEvent, Event, EventQuery
from ride_machine.schema.status import MachineState
from tests.integration.support import fast_daemon, prepare

RIDERS = 4
PER_RIDER = 150
TOGGLES = 6
BOUND_S = 20.0
MIX = [Command.HOME, Command.STOP, Command.PAUSE, Command.RESUME, Command.CHECK_HOME]
CHECKS = {Command.CHECK_HOME.value, Command.CHECK_CALIBRATION.value}


def _storm(
    rider: Rider, name: str, sent: list[str], replies: Counter[str], errors: list[str]
) -> None:
    try:
        _send_all(rider, name, sent, replies, errors)
    except Exception as exc:  # noqa: BLE001 - reported by the test thread
        errors.append(f"{name}: {exc!r}")


def _send_all(
    rider: Rider, name: str, sent: list[str], replies: Counter[str], errors: list[str]
) -> None:
    for i, command in zip(range(PER_RIDER), itertools.cycle(MIX), strict=False):
        tid = f"{name}-{i}"
        sent.append(tid)
        got = list(
            rider.session.get(
                f"{rider.base}/cmd/{command.key}",
                payload=pack({"transaction_id": tid}),
                encoding=Format.MSGPACK.value,
                timeout=5.0,
            )
        )
        for r in got:
            sample = r.ok if r.ok is not None else r.err
            assert sample is not None
            reply = decode(Reply, sample.payload.to_bytes(), Format.MSGPACK)
            replies[reply.transaction_id or "?"] += 1
        if len(got) != 1:
            errors.append(f"{tid}: {len(got)} replies")


def _wait_estop(rider: Rider, pressed: bool) -> None:
    """Until a published status shows the input as asked (a scan cycle has seen it)."""
    deadline = time.monotonic() + BOUND_S
    while rider.status().estop.active is not pressed:
        assert time.monotonic() < deadline, f"E-stop never seen {'pressed' if pressed else 'up'}"


def _events(rider: Rider, after: int, commands: int) -> list[Event]:
    """The history after `after` once every command of the storm is in it (written
    asynchronously), in small pages (a 500-event page of commands is over the 64 KiB limit)."""
    deadline = time.monotonic() + BOUND_S
    while True:
        events = rider.events(EventQuery(since=after + 1, limit=100))
        done = sum(1 for e in events if isinstance(e.details, CommandEvent))
        if done >= commands or time.monotonic() > deadline:
            return events


@pytest.mark.hazard("H09", "H47")
def test_estop_first_and_one_reply_each_under_a_command_storm(tmp_path: Path) -> None:
    with contextlib.ExitStack() as stack:
        daemon = stack.enter_context(fast_daemon(tmp_path))
        operator = stack.enter_context(daemon.rider())
        assert prepare(operator).state is MachineState.IDLE
        start_seq = operator.events(last=1)[-1].seq
        riders = [stack.enter_context(daemon.rider()) for _ in range(RIDERS)]
        sent: list[list[str]] = [[] for _ in riders]
        replies: Counter[str] = Counter()
        errors: list[str] = []
        threads = [
            threading.Thread(target=_storm, args=(r, f"r{n}", sent[n], replies, errors))
            for n, r in enumerate(riders)
        ]
        for t in threads:
            t.start()
        for _ in range(TOGGLES):
            operator.sim("estop", pressed=True)
            _wait_estop(operator, True)
            operator.sim("estop", pressed=False)
            _wait_estop(operator, False)
        for t in threads:
            t.join(timeout=60.0)
            assert not t.is_alive()
        tids = [tid for s in sent for tid in s]
        assert errors == []
        assert replies == Counter(dict.fromkeys(tids, 1))
        history = _events(operator, start_seq, len(tids))
        _assert_estop_first(history)
        acted = Counter(
            e.details.transaction_id
            for e in history
            if isinstance(e.details, CommandEvent) and not e.details.repeat
        )
        assert {tid: acted[tid] for tid in tids} == dict.fromkeys(tids, 1)


def _assert_estop_first(history: list[Event]) -> None:
    """Each E-stop press comes before every command of its cycle and the later ones; while the
    input is pressed, every command but the read-only checks is refused ESTOP_ACTIVE."""
    presses = refused = 0
    pressed_at: int | None = None
    for e in history:
        d = e.details
        if isinstance(d, EstopEvent) and d.kind == "estop_pressed":
            presses += 1
            pressed_at = e.cycle
        elif isinstance(d, EstopEvent) and d.kind == "estop_released":
            pressed_at = None
        elif isinstance(d, CommandEvent):
            assert e.cycle is not None
            if pressed_at is not None:
                assert e.cycle >= pressed_at, f"a command of an earlier cycle after the press: {e}"
                if d.command not in CHECKS:
                    assert (d.accepted, d.code) == (False, "ESTOP_ACTIVE"), e
                    refused += 1
    for press in (e for e in history if getattr(e.details, "kind", "") == "estop_pressed"):
        late = [
            e
            for e in history
            if isinstance(e.details, CommandEvent)
            and e.cycle is not None
            and press.cycle is not None
            and e.cycle >= press.cycle
            and e.seq < press.seq
        ]
        assert late == [], f"commands of the E-stop's cycle recorded before it: {late}"
    assert presses == TOGGLES
    assert refused > 0, "the storm never overlapped a press: nothing was tested"
