"""`rider home|pause|resume|stop|calibrate|start [--wait]`: the commands that move (or stop) a
ride, and `--wait`: the motion's completion notice, told on stderr while it is awaited (exit 1
unless it ended DONE, 6 once the machine is unheard for `--link-limit`). The handlers; their
parsers: rider/subcommands/parsers.py."""

from __future__ import annotations

import argparse
import json
import sys
import tomllib
from pathlib import Path

from pydantic import ValidationError

from ride_machine.rider.blocking import Rider
from ride_machine.rider.errors import RiderError
from ride_machine.rider.exits import EXIT_OK, EXIT_REFUSED, UsageError
from ride_machine.rider.formats import emit, fmt_completion, fmt_reply, fmt_status
from ride_machine.rider.text import printable
from ride_machine.rider.waiting import WaitTeller, quiet_limit
from ride_machine.schema.commands import Reply, Session
from ride_machine.schema.completion import Outcome
from ride_machine.schema.status import MachineState


def motion(args: argparse.Namespace, rider: Rider) -> int:
    """Send the command; with `--wait`, wait for how its motion ended."""
    if args.cmd == "calibrate":
        reply = rider.calibrate_tilt() if args.axis == "tilt" else rider.calibrate_rotate()
    elif args.cmd == "start":
        session = load_session(args.session) if args.session else None
        reply = rider.start(session)
    else:
        reply = getattr(rider, args.cmd)()
    emit(reply, args.json, fmt_reply)
    if not getattr(args, "wait", False):
        return EXIT_OK
    return _wait(args, rider, reply)


def _wait(args: argparse.Namespace, rider: Rider, reply: Reply) -> int:
    if args.cmd in ("pause", "stop"):
        # Their reply is their completion (Stop's ends the motion it stopped: STOPPED); show
        # the first status of the cycle that answered, not one published before it.
        final = rider.wait_for(set(MachineState), timeout=args.wait_timeout, after=reply.timecode)
        emit(final, args.json, fmt_status)
        return EXIT_OK
    tid = reply.transaction_id
    if args.cmd == "resume":
        motion_ref = rider.status().motion  # Resume continues a motion: wait for its notice
        if motion_ref is None:
            final = rider.status()
            emit(final, args.json, fmt_status)
            return EXIT_OK
        tid = motion_ref.transaction_id
    assert tid is not None
    teller = WaitTeller(rider.machine_id, link=rider.no_link_hint)
    notice = rider.wait_done(
        tid,
        timeout=args.wait_timeout,
        on_status=teller.on_status,
        on_silence=teller.on_silence,
        quiet_s=quiet_limit(rider.timeout, _heartbeat_s(rider)),
        link_limit=args.link_limit,
    )
    emit(notice, args.json, fmt_completion)
    final = rider.status()
    emit(final, args.json, fmt_status)
    if notice.outcome != Outcome.DONE:
        why = printable(f"{notice.command} {notice.outcome}: {notice.reason}")
        print(f"rider: {why}", file=sys.stderr)
        return EXIT_REFUSED
    return EXIT_OK


def _heartbeat_s(rider: Rider) -> float:
    """The machine's status heartbeat (`Status.heartbeat_s`, which every login may read;
    1 s when the machine does not say)."""
    try:
        return rider.status().heartbeat_s or 1.0
    except RiderError:
        return 1.0


def load_session(path: Path) -> Session:
    try:
        text = path.read_text()
        data = (
            json.loads(text)
            if path.suffix == ".json" or text.lstrip().startswith("{")
            else tomllib.loads(text)
        )
        return Session.model_validate(data)
    except OSError as exc:
        raise UsageError(f"{path}: cannot read ({exc.strerror})") from exc
    except (ValueError, ValidationError) as exc:
        raise UsageError(f"{path}: not a valid session: {exc}") from exc
