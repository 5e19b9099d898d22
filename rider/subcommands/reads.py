"""`rider status|check|io|axes|diag|validate|done`: what the machine says now (the handlers;
their parsers: rider/subcommands/parsers.py)."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from typing import TypeVar

from ride_machine.rider.blocking import Rider
from ride_machine.rider.exits import EXIT_OK, EXIT_REFUSED, UsageError
from ride_machine.rider.formats import (
    emit,
    fmt_axis,
    fmt_check,
    fmt_completion,
    fmt_diag,
    fmt_findings,
    fmt_io,
    fmt_status,
)
from ride_machine.rider.subcommands import Handler
from ride_machine.schema.axes import AxisRecord
from ride_machine.schema.commands import CheckResult
from ride_machine.schema.completion import Outcome

T = TypeVar("T")


def _reading(read: Callable[[Rider], T], human: Callable[[T], str]) -> Handler:
    """`rider NAME`: what `read` gets from the machine, printed by `human` (or as JSON)."""

    def handler(args: argparse.Namespace, rider: Rider) -> int:
        emit(read(rider), args.json, human)
        return EXIT_OK

    return handler


def _fmt_axes(records: list[AxisRecord]) -> str:
    return "\n".join(fmt_axis(a) for a in records)


status = _reading(Rider.status, fmt_status)
io = _reading(Rider.io, fmt_io)
axes = _reading(Rider.axes, _fmt_axes)


def check(args: argparse.Namespace, rider: Rider) -> int:
    result: CheckResult = (
        rider.check_calibration() if args.what == "calibration" else rider.check_home()
    )
    emit(result, args.json, lambda r: fmt_check(args.what, r))
    return EXIT_OK if result.ok else EXIT_REFUSED


def diag(args: argparse.Namespace, rider: Rider) -> int:
    emit(rider.diag(reset=args.reset), args.json, fmt_diag)
    return EXIT_OK


def validate(args: argparse.Namespace, rider: Rider) -> int:
    candidate = None
    if args.config is not None:
        try:
            candidate = args.config.read_bytes()
        except OSError as exc:
            raise UsageError(f"{args.config}: cannot read ({exc.strerror})") from exc
    findings = rider.validate(candidate)
    emit(findings, args.json, fmt_findings)
    return EXIT_OK if findings.ok else EXIT_REFUSED


def done(args: argparse.Namespace, rider: Rider) -> int:
    """`rider done [TID]`: how a motion ended (late Riders), or every remembered notice."""
    if args.transaction_id is None:
        notices = rider.recent_completions()
        emit(notices, args.json, lambda ns: "\n".join(fmt_completion(n) for n in ns))
        return EXIT_OK
    found = rider.done(args.transaction_id)
    if found is None:
        print(f"rider: {args.transaction_id} has not ended yet", file=sys.stderr)
        return EXIT_REFUSED
    emit(found, args.json, fmt_completion)
    return EXIT_OK if found.outcome == Outcome.DONE else EXIT_REFUSED
