"""Every sub-command's parser, apart from its handler: `rider --help` and bad usage are answered
from argparse alone, before the client, Zenoh or a wire model is loaded. Each parser carries
its handler by name (`Lazy(kind, name)`), loaded when the command runs; one that sends a
command (`cmd/…`: a motion, a check) says so (`sends_command`): without `--machine` its lookup
waits longer (rider/discovery.py's `MOTION_SETTLE_S`)."""

from __future__ import annotations

import argparse
from pathlib import Path

from ride_machine.rider.subcommands import Lazy, Subparsers
from ride_machine.schema.event_kinds import EventKind

LINK_LIMIT_S = 30.0
"""`--link-limit`'s default: the wait gives up after this long without a word from the machine
(the deadman paused a ride this Rider supervised after `rider_loss.timeout_s`)."""

WAIT_HELP = "wait for the completion notice of this command's motion (exit 1 unless DONE)"


# -------------------------------------------------------------------- reads (what is now)
def add_status(sub: Subparsers[argparse.ArgumentParser]) -> None:
    sub.add_parser("status", help="the machine's status").set_defaults(func=Lazy("reads", "status"))


def add_io(sub: Subparsers[argparse.ArgumentParser]) -> None:
    sub.add_parser("io", help="all IO points").set_defaults(func=Lazy("reads", "io"))


def add_axes(sub: Subparsers[argparse.ArgumentParser]) -> None:
    sub.add_parser("axes", help="the latest axis records").set_defaults(func=Lazy("reads", "axes"))


def add_check(sub: Subparsers[argparse.ArgumentParser]) -> None:
    chk = sub.add_parser("check", help="check calibration or home")
    chk.add_argument("what", choices=["calibration", "home"])
    chk.set_defaults(func=Lazy("reads", "check"), sends_command=True)


def add_diag(sub: Subparsers[argparse.ArgumentParser]) -> None:
    d = sub.add_parser("diag", help="scan-loop diagnostics")
    d.add_argument("--reset", action="store_true", help="reset min/max and overrun counters")
    d.set_defaults(func=Lazy("reads", "diag"))


def add_validate(sub: Subparsers[argparse.ArgumentParser]) -> None:
    v = sub.add_parser("validate", help="check the running config, or a candidate file")
    v.add_argument("--config", type=Path, help="candidate config (TOML or JSON)")
    v.set_defaults(func=Lazy("reads", "validate"))


def add_done(sub: Subparsers[argparse.ArgumentParser]) -> None:
    dn = sub.add_parser("done", help="how a motion ended (its completion notice)")
    dn.add_argument(
        "transaction_id",
        nargs="?",
        type=_transaction_id,
        help="the command's transaction id (default: all recent)",
    )
    dn.set_defaults(func=Lazy("reads", "done"))


def _transaction_id(text: str) -> str:
    """An id a machine can have (it names the key `done/<id>`: no wildcard, no empty part)."""
    # The wire's own rule, loaded only when an id is given.
    from pydantic import TypeAdapter, ValidationError

    from ride_machine.schema.commands import TransactionId

    try:
        return TypeAdapter(TransactionId).validate_python(text)
    except ValidationError:
        raise argparse.ArgumentTypeError(
            f"{text!r} is not a transaction_id (1-64 letters, digits and ._:@+- in /-parts)"
        ) from None


# ------------------------------------------------------------ live (as it happens)
def add_watch(sub: Subparsers[argparse.ArgumentParser]) -> None:
    w = sub.add_parser("watch", help="live status / IO / axis updates")
    w.add_argument("--keys", default="status,io/**,axis/**", help="comma-separated keys")
    w.add_argument(
        "--for", dest="duration", type=float, default=None, help="stop after this many seconds"
    )
    w.add_argument(
        "--until",
        nargs="*",
        default=None,
        metavar="STATE",
        help="stop when the machine reaches one of these states",
    )
    w.set_defaults(func=Lazy("live", "watch"))


def add_machines(sub: Subparsers[argparse.ArgumentParser]) -> None:
    m = sub.add_parser("machines", help="machines alive on the network")
    m.add_argument("--watch", action="store_true", help="follow arrivals and departures")
    m.add_argument("--for", dest="duration", type=float, default=None)
    m.set_defaults(func=Lazy("live", "machines"))


def add_events(sub: Subparsers[argparse.ArgumentParser]) -> None:
    ev = sub.add_parser("events", help="the machine's event history (what happened, when, who)")
    ev.add_argument(
        "--since", help="a seq number, an age (30m, 12h, 7d) or a local time (2026-11-27T14:00)"
    )
    ev.add_argument("--until", help="as --since")
    ev.add_argument(
        "--kind",
        action="append",
        default=[],
        help=f"only these kinds (repeatable or comma-separated): {', '.join(EventKind)}",
    )
    ev.add_argument("--last", type=int, help="only the newest N (default 20 without --since)")
    ev.add_argument("--follow", action="store_true", help="then print new events as they happen")
    ev.add_argument("--for", dest="duration", type=float, help="with --follow: stop after S s")
    ev.add_argument(
        "--summary", action="store_true", help="sessions, ride time, E-stops, faults by code"
    )
    ev.add_argument("--json", action="store_true", default=argparse.SUPPRESS, help="JSON lines")
    ev.set_defaults(func=Lazy("live", "events"))


# ------------------------------------------------------------------ motion (what moves)
def add_motions(sub: Subparsers[argparse.ArgumentParser]) -> None:
    """`home`, `pause`, `resume`, `stop`, `calibrate AXIS` and `start [--session FILE]`."""
    for name, text in (
        ("home", "home both axes (tilt, then rotate)"),
        ("pause", "pause motion, relays off"),
        ("resume", "resume after pause or a released E-stop"),
        ("stop", "stop, clear the session, DONE"),
    ):
        _wait_options(sub.add_parser(name, help=text))
    cal = sub.add_parser("calibrate", help="calibrate an axis")
    cal.add_argument("axis", choices=["tilt", "rotate"])
    _wait_options(cal)
    st = sub.add_parser("start", help="start a session (default: tilt 45°, rotate CW x3)")
    st.add_argument("--session", type=Path, help="session file (JSON or TOML)")
    _wait_options(st)


def _wait_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--wait", action="store_true", help=WAIT_HELP)
    p.add_argument(
        "--wait-timeout", type=float, default=600.0, help="give up waiting after this many s"
    )
    p.add_argument(
        "--link-limit",
        type=float,
        default=LINK_LIMIT_S,
        metavar="S",
        help="give up waiting (exit 6) after S seconds without a word from the machine"
        f" (default {LINK_LIMIT_S:g})",
    )
    p.set_defaults(func=Lazy("motion", "motion"), sends_command=True)


# ------------------------------------------------------------ settings (what is set)
def add_calibration(sub: Subparsers[argparse.ArgumentParser]) -> None:
    cb = sub.add_parser("calibration", help="calibration values; `set` enters them by hand")
    cb.set_defaults(func=Lazy("settings", "calibration"))
    cbs = cb.add_subparsers(dest="calibration_cmd")
    cs = cbs.add_parser("set", help="enter values by hand (recorded as manual)")
    cs.add_argument("--tilt-offset", type=float, help="tilt offset in raw counts (at 0°)")
    cs.add_argument("--tilt-gain", type=float, help="tilt gain in counts per degree")
    cs.add_argument("--rotate-revolution-s", type=float, help="one revolution, seconds")
    cs.add_argument("--rotate-home-arc", type=float, help="home-switch arc, degrees")
    cs.set_defaults(func=Lazy("settings", "set_calibration"))


def add_params(sub: Subparsers[argparse.ArgumentParser]) -> None:
    pr = sub.add_parser("params", help="online parameters")
    prs = pr.add_subparsers(dest="params_cmd", required=True)
    prs.add_parser("list").set_defaults(func=Lazy("settings", "list_params"))
    g = prs.add_parser("get")
    g.add_argument("name")
    g.set_defaults(func=Lazy("settings", "get_param"))
    s = prs.add_parser("set")
    s.add_argument("name")
    s.add_argument("value", help="JSON value (number, true/false, or a string)")
    s.add_argument("--persist", action="store_true", help="keep it across restarts")
    s.set_defaults(func=SET_PARAM)
    r = prs.add_parser("reset")
    r.add_argument("name")
    r.set_defaults(func=Lazy("settings", "reset_param"))


SET_PARAM = Lazy("settings", "set_param")
"""`params set`'s handler (`rider fastdata set …` runs it too)."""


def add_sim(sub: Subparsers[argparse.ArgumentParser]) -> None:
    sim_parser = sub.add_parser("sim", help="simulator fault injection")
    sim_parser.add_argument(
        "fault", choices=["estop", "release", "home", "tilt_ai", "stall", "clear", "world"]
    )
    sim_parser.add_argument(
        "args", nargs="*", help="e.g. `home rotate open`, `tilt_ai frozen`, `stall tilt`"
    )
    sim_parser.set_defaults(func=Lazy("settings", "sim"))
