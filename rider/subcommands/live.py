"""`rider watch`, `rider machines [--watch]` and `rider events [--follow]`: what happens, as it
happens (each with `--for S` to stop after S seconds). The handlers; their parsers:
rider/subcommands/parsers.py."""

from __future__ import annotations

import argparse
import json
import sys
import time

from ride_machine.rider.blocking import Rider
from ride_machine.rider.exits import EXIT_DUPLICATE, EXIT_NO_REPLY, EXIT_OK, UsageError
from ride_machine.rider.formats import emit, fmt_event, fmt_machine, fmt_summary, fmt_update
from ride_machine.rider.text import printable, shown
from ride_machine.schema.events import EventQuery, query_of
from ride_machine.schema.status import MachineState, Status


def watch(args: argparse.Namespace, rider: Rider) -> int:
    keys = [k.strip() for k in args.keys.split(",") if k.strip()]
    until = {MachineState(s.upper()) for s in args.until} if args.until else None
    deadline = None if args.duration is None else time.monotonic() + args.duration
    last_seq = -1  # seq of the last status printed
    # With a deadline, a quiet half second ends one `rider.watch` so the deadline is checked;
    # the next one starts with the current status again, skipped when it was already shown.
    while deadline is None or time.monotonic() < deadline:
        for update in rider.watch(keys, timeout=0.5 if deadline else None):
            if isinstance(update, Status):
                if update.seq == last_seq:
                    continue
                last_seq = update.seq
            print(update.model_dump_json() if args.json else fmt_update(shown(update)), flush=True)
            if until and isinstance(update, Status) and update.state in until:
                return EXIT_OK
            if deadline is not None and time.monotonic() > deadline:
                break
    return EXIT_OK if until is None else EXIT_NO_REPLY


def machines(args: argparse.Namespace, rider: Rider) -> int:
    found = rider.machines()
    # Followed after the listing, with history (changes against the list are printed): the
    # listing's discovery declares and undeclares a liveliness subscriber on the same key, and
    # zenoh 1.10 (client mode) then stops giving new tokens to one declared before it.
    changes = rider.follow_machines(timeout=0.5, history=True) if args.watch else None
    lines = [fmt_machine(m) for m in found]
    none = f"no machines alive{rider.no_link_hint() if not found else ''}"
    emit([m.__dict__ for m in found], args.json, lambda _: "\n".join(lines) or none)
    if not found.complete:
        print(f"rider: the list may be incomplete: {found.note}", file=sys.stderr)
    conflict = any(m.conflict for m in found)
    if changes is None:
        return EXIT_DUPLICATE if conflict else EXIT_OK
    sys.stdout.flush()
    alive = {m.id for m in found}
    deadline = None if args.duration is None else time.monotonic() + args.duration
    for change in changes:
        if change is not None and change[1] != (change[0] in alive):
            mid, up_now = change  # e.g. one that came and went before the listing: skipped
            if up_now:
                alive.add(mid)
            else:
                alive.discard(mid)
            event = {"id": mid, "alive": up_now, "time": time.time()}
            text = f"{'+' if up_now else '-'} {printable(mid)} {'arrived' if up_now else 'left'}"
            print(json.dumps(event) if args.json else text, flush=True)
        if deadline is not None and time.monotonic() > deadline:
            break
    return EXIT_OK


def event_query(args: argparse.Namespace, now: float) -> EventQuery:
    last = args.last
    if last is None and args.since is None and not args.summary:
        last = 20
    try:
        return query_of(args.since, args.until, args.kind, now, last)
    except ValueError as exc:
        raise UsageError(str(exc)) from None


def events(args: argparse.Namespace, rider: Rider) -> int:
    now = time.time()
    query = event_query(args, now)
    many = "*" in rider.machine_id
    if args.summary:
        summaries = rider.events_summary(query.since_time, query.until_time)
        emit(summaries, args.json, lambda xs: "\n\n".join(fmt_summary(x) for x in xs))
        return EXIT_OK
    if not args.follow:
        for event in rider.events(query):
            print(event.model_dump_json() if args.json else fmt_event(shown(event), many))
        return EXIT_OK
    deadline = None if args.duration is None else time.monotonic() + args.duration
    for item in rider.follow_events(query, timeout=0.5):
        if item is not None:
            print(item.model_dump_json() if args.json else fmt_event(shown(item), many), flush=True)
        if deadline is not None and time.monotonic() > deadline:
            break
    return EXIT_OK
