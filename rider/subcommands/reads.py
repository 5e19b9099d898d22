"""`rider status|check|io|axes|diag|validate|done`: what the machine says now."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

from pydantic import TypeAdapter, ValidationError

from rider.blocking import Rider
from rider.exits import EXIT_OK, EXIT_REFUSED, UsageError
from rider.formats import (
    emit,
    fmt_axis,
    fmt_check,
    fmt_completion,
    fmt_diag,
    fmt_findings,
    fmt_io,
    fmt_status,
)
from rider.subcommands import Subparsers
from schema.axes import AxisRecord
from schema.commands import CheckResult, TransactionId
from schema.completion import Outcome

T = TypeVar("T")


def add_status(sub: Subparsers[argparse.ArgumentParser]) -> None:
    _reading(sub, "status", "the machine's status", Rider.status, fmt_status)


def add_io(sub: Subparsers[argparse.ArgumentParser]) -> None:
    _reading(sub, "io", "all IO points", Rider.io, fmt_io)


def add_axes(sub: Subparsers[argparse.ArgumentParser]) -> None:
    _reading(sub, "axes", "the latest axis records", Rider.axes, _fmt_axes)


def _fmt_axes(records: list[AxisRecord]) -> str:
    return "\n".join(fmt_axis(a) for a in records)


def _reading(
    sub: Subparsers[argparse.ArgumentParser],
    name: str,
    text: str,
    read: Callable[[Rider], T],
    human: Callable[[T], str],
) -> None:
    """`rider NAME`: what `read` gets from the machine, printed by `human` (or as JSON)."""

    def handler(args: argparse.Namespace, rider: Rider) -> int:
        emit(read(rider), args.json, human)
        return EXIT_OK

    sub.add_parser(name, help=text).set_defaults(func=handler)


def add_check(sub: Subparsers[argparse.ArgumentParser]) -> None:
    chk = sub.add_parser("check", help="check calibration or home")
    chk.add_argument("what", choices=["calibration", "home"])
    chk.set_defaults(func=check)


def check(args: argparse.Namespace, rider: Rider) -> int:
    result: CheckResult = (
        rider.check_calibration() if args.what == "calibration" else rider.check_home()
    )
    emit(result, args.json, lambda r: fmt_check(args.what, r))
    return EXIT_OK if result.ok else EXIT_REFUSED


def add_diag(sub: Subparsers[argparse.ArgumentParser]) -> None:
    d = sub.add_parser("diag", help="scan-loop diagnostics")
    d.add_argument("--reset", action="store_true", help="reset min/max and overrun counters")
    d.set_defaults(func=diag)


def diag(args: argparse.Namespace, rider: Rider) -> int:
    emit(rider.diag(reset=args.reset), args.json, fmt_diag)
    return EXIT_OK


def add_validate(sub: Subparsers[argparse.ArgumentParser]) -> None:
    v = sub.add_parser("validate", help="check the running config, or a candidate file")
    v.add_argument("--config", type=Path, help="candidate config (TOML or JSON)")
    v.set_defaults(func=validate)


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


def add_done(sub: Subparsers[argparse.ArgumentParser]) -> None:
    dn = sub.add_parser("done", help="how a motion ended (its completion notice)")
    dn.add_argument(
        "transaction_id",
        nargs="?",
        type=_transaction_id,
        help="the command's transaction id (default: all recent)",
    )
    dn.set_defaults(func=done)


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


def _transaction_id(text: str) -> str:
    """An id a machine can have (it names the key `done/<id>`: no wildcard, no empty part)."""
    try:
        return TypeAdapter(TransactionId).validate_python(text)
    except ValidationError:
        raise argparse.ArgumentTypeError(
            f"{text!r} is not a transaction_id (1-64 letters, digits and ._:@+- in /-parts)"
        ) from None
