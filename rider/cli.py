"""The `rider` command: operate a machine from a terminal or a script.

Exit codes: 0 done; 1 the machine refused (its error is printed), or a motion `--wait`ed for
ended otherwise than DONE; 2 bad usage or input; 3 no reply (machine or network down); 4
several machines alive and none named; 5 more than one session answers for the machine id
(two daemons share it: DUPLICATE_ID); 6 `--wait` heard nothing from the machine for
`--link-limit` seconds (the link stayed down: a ride this Rider supervised was paused by the
machine's deadman; see `rider status` once the link is back).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
import tomllib
from collections.abc import Callable, Sequence
from datetime import datetime
from pathlib import Path
from typing import Any, TypeVar

from pydantic import BaseModel, TypeAdapter, ValidationError

from rider.client import (
    AmbiguousMachine,
    BadCredentials,
    BadRuntime,
    CommandRefused,
    DuplicateMachine,
    LinkLost,
    MachineTimeout,
    NoMachine,
    Rider,
    RiderError,
    Update,
    env_connect,
)
from rider.text import printable, shown
from rider.waiting import LINK_LIMIT_S, WaitTeller, quiet_limit
from schema.axes import AxisRecord, PnStatus
from schema.calibration import CalibrationRecord, RotateCalibrationSet, TiltCalibrationSet
from schema.commands import CheckResult, Reply, Session, TransactionId
from schema.completion import Completion, Outcome
from schema.diag import CycleDiag
from schema.events import (
    Event,
    EventKind,
    EventQuery,
    EventSummary,
    describe,
    query_of,
)
from schema.findings import Findings
from schema.io import IoValue
from schema.params import ParamValue
from schema.status import MachineState, Status

EXIT_OK = 0
EXIT_REFUSED = 1
EXIT_USAGE = 2
EXIT_NO_REPLY = 3
EXIT_AMBIGUOUS = 4
EXIT_DUPLICATE = 5
EXIT_LINK_LOST = 6


T = TypeVar("T")


class UsageError(Exception):
    """Bad arguments or an unreadable input file."""


def _machine_id(text: str) -> str:
    """One key chunk (`*` allowed: reads across machines); checked before any Zenoh call."""
    if not text or "/" in text:
        raise argparse.ArgumentTypeError(f"{text!r} is not a machine id (one key part, no '/')")
    return text


def _transaction_id(text: str) -> str:
    """An id a machine can have (it names the key `done/<id>`: no wildcard, no empty part)."""
    try:
        return TypeAdapter(TransactionId).validate_python(text)
    except ValidationError:
        raise argparse.ArgumentTypeError(
            f"{text!r} is not a transaction_id (1-64 letters, digits and ._:@+- in /-parts)"
        ) from None


def _positive_s(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"{text!r} is not a positive number of seconds")
    return value


ZENOH_THREADS_MAX = 64
"""As the daemon's `bus.zenoh_threads`."""


def _zenoh_threads(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = -1
    if not 0 <= value <= ZENOH_THREADS_MAX:
        raise argparse.ArgumentTypeError(
            f"{text!r} is not a thread count from 0 (Zenoh's own layout) to {ZENOH_THREADS_MAX}"
        )
    return value


def build_parser() -> argparse.ArgumentParser:  # noqa: PLR0915 - argparse declarations, one statement per option
    p = argparse.ArgumentParser(
        prog="rider", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument(
        "--connect",
        action="append",
        default=[],
        help="Zenoh endpoint of the machine (default tcp/127.0.0.1:7447 or $RIDER_CONNECT)",
    )
    p.add_argument("--zenoh-config", type=Path, help="zenoh.json5 (shared with the daemon)")
    p.add_argument(
        "--machine",
        "-m",
        type=_machine_id,
        default=None,
        help="machine id (default: the only machine alive)",
    )
    p.add_argument("--prefix", default="machine", help="key prefix (default: machine)")
    p.add_argument("--timeout", type=_positive_s, default=2.0, help="reply timeout in seconds")
    p.add_argument(
        "--zenoh-threads",
        type=_zenoh_threads,
        default=1,
        help="Zenoh's worker threads in this process (default 1, as the daemon; 0: Zenoh's own"
        " six; $ZENOH_RUNTIME wins)",
    )
    p.add_argument("--json", action="store_true", help="print JSON instead of tables")
    sub = p.add_subparsers(dest="cmd", required=True)

    sub.add_parser("status", help="the machine's status")
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
    wait_help = "wait for the completion notice of this command's motion (exit 1 unless DONE)"
    for name, text in (
        ("home", "home both axes (tilt, then rotate)"),
        ("pause", "pause motion, relays off"),
        ("resume", "resume after pause or a released E-stop"),
        ("stop", "stop, clear the session, DONE"),
    ):
        c = sub.add_parser(name, help=text)
        _wait_options(c, wait_help)
    cal = sub.add_parser("calibrate", help="calibrate an axis")
    cal.add_argument("axis", choices=["tilt", "rotate"])
    _wait_options(cal, wait_help)
    st = sub.add_parser("start", help="start a session (default: tilt 45°, rotate CW x3)")
    st.add_argument("--session", type=Path, help="session file (JSON or TOML)")
    _wait_options(st, wait_help)
    cb = sub.add_parser("calibration", help="calibration values; `set` enters them by hand")
    cbs = cb.add_subparsers(dest="calibration_cmd")
    cs = cbs.add_parser("set", help="enter values by hand (recorded as manual)")
    cs.add_argument("--tilt-offset", type=float, help="tilt offset in raw counts (at 0°)")
    cs.add_argument("--tilt-gain", type=float, help="tilt gain in counts per degree")
    cs.add_argument("--rotate-revolution-s", type=float, help="one revolution, seconds")
    cs.add_argument("--rotate-home-arc", type=float, help="home-switch arc, degrees")
    dn = sub.add_parser("done", help="how a motion ended (its completion notice)")
    dn.add_argument(
        "transaction_id",
        nargs="?",
        type=_transaction_id,
        help="the command's transaction id (default: all recent)",
    )
    chk = sub.add_parser("check", help="check calibration or home")
    chk.add_argument("what", choices=["calibration", "home"])
    sub.add_parser("io", help="all IO points")
    sub.add_parser("axes", help="the latest axis records")
    d = sub.add_parser("diag", help="scan-loop diagnostics")
    d.add_argument("--reset", action="store_true", help="reset min/max and overrun counters")
    pr = sub.add_parser("params", help="online parameters")
    prs = pr.add_subparsers(dest="params_cmd", required=True)
    prs.add_parser("list")
    g = prs.add_parser("get")
    g.add_argument("name")
    s = prs.add_parser("set")
    s.add_argument("name")
    s.add_argument("value", help="JSON value (number, true/false, or a string)")
    s.add_argument("--persist", action="store_true", help="keep it across restarts")
    r = prs.add_parser("reset")
    r.add_argument("name")
    v = sub.add_parser("validate", help="check the running config, or a candidate file")
    v.add_argument("--config", type=Path, help="candidate config (TOML or JSON)")
    m = sub.add_parser("machines", help="machines alive on the network")
    m.add_argument("--watch", action="store_true", help="follow arrivals and departures")
    m.add_argument("--for", dest="duration", type=float, default=None)
    sim = sub.add_parser("sim", help="simulator fault injection")
    sim.add_argument(
        "fault", choices=["estop", "release", "home", "tilt_ai", "stall", "clear", "world"]
    )
    sim.add_argument(
        "args", nargs="*", help="e.g. `home rotate open`, `tilt_ai frozen`, `stall tilt`"
    )
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
    # These parse their own options (rider/fastdata.py, rider/ui/app.py, rider/gateway/cli.py).
    sub.add_parser("fastdata", help="read the FastData UDP axis stream", add_help=False)
    sub.add_parser("ui", help="serve the operator web UI", add_help=False)
    sub.add_parser("gateway", help="OPC UA and Prometheus for the plant", add_help=False)
    return p


def _wait_options(p: argparse.ArgumentParser, text: str) -> None:
    p.add_argument("--wait", action="store_true", help=text)
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


# ------------------------------------------------------------------------------- printing
def emit(obj: T, as_json: bool, human: Callable[[T], str]) -> None:
    """JSON as the machine sent it, or `human(obj)` with every wire string made printable."""
    if as_json:
        if isinstance(obj, BaseModel):
            print(obj.model_dump_json())
        elif isinstance(obj, list):
            print(
                json.dumps(
                    [o.model_dump(mode="json") if isinstance(o, BaseModel) else o for o in obj]
                )
            )
        else:
            print(json.dumps(obj))
    else:
        print(human(shown(obj)))


def fmt_status(s: Status) -> str:
    rows = [
        ("machine", s.machine_id),
        ("state", f"{s.state}" + (f" (from {s.previous_state})" if s.previous_state else "")),
        ("calibrated", f"tilt={_yn(s.calibrated.tilt)} rotate={_yn(s.calibrated.rotate)}"),
        ("home", f"tilt={_yn(s.homed.tilt)} rotate={_yn(s.homed.rotate)}"),
        ("e-stop", f"active={_yn(s.estop.active)} latched={_yn(s.estop.latched)}"),
        ("tilt", "?" if s.tilt_deg is None else f"{s.tilt_deg:.1f}°"),
        ("rotate", "?" if s.rotate_deg is None else f"{s.rotate_deg:.0f}°"),
    ]
    if s.session is not None:
        p = s.session
        rows.append(
            (
                "session",
                f"{p.name} step {min(p.step_index + 1, p.step_count)}/{p.step_count}"
                f" ({p.step_kind or 'done'})"
                f" revolutions {p.revolutions_done}/{p.revolutions_total}",
            )
        )
    if s.fault is not None:
        rows.append(("fault", f"{s.fault.code}: {s.fault.message}"))
    for warning in s.warnings:
        rows.append(("warning", warning))
    rows.append(("seq/uptime", f"{s.seq} / {s.uptime_s:.1f} s"))
    width = max(len(k) for k, _ in rows)
    return "\n".join(f"{k:<{width}}  {v}" for k, v in rows)


def fmt_reply(r: Reply) -> str:
    line = f"{r.command}: {r.code} -> state {r.state}"
    if r.result is not None:
        line += f" ok={_yn(r.result.ok)} tilt={_yn(r.result.tilt)} rotate={_yn(r.result.rotate)}"
    return line


def fmt_calibration(c: CalibrationRecord) -> str:
    def how(source: str | None, at: float | None) -> str:
        when = "?" if at is None else time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(at))
        return f"({source or 'measured'}, {when})"

    t, r = c.tilt, c.rotate
    tilt = (
        "not calibrated"
        if t is None
        else f"offset {t.offset_counts:.1f} counts, gain {t.gain_counts_per_deg:.3f} counts/°"
        f" {how(t.source, t.at)}"
    )
    rotate = (
        "not calibrated"
        if r is None
        else f"revolution {r.revolution_s:.3f} s ({r.speed_dps:.1f}°/s), home arc"
        f" {r.home_arc_deg:.1f}° {how(r.source, r.at)}"
    )
    return f"tilt    {tilt}\nrotate  {rotate}"


def fmt_completion(n: Completion) -> str:
    code = f" {n.code}" if n.code else ""
    return f"{n.command} {n.transaction_id}: {n.outcome}{code} -> state {n.state}" + (
        f" ({n.reason})" if n.reason else ""
    )


def fmt_io(points: list[IoValue]) -> str:
    lines = [f"{'kind':4} {'name':12} {'channel':14} value"]
    for p in points:
        value = ("ON" if p.value else "off") if isinstance(p.value, bool) else str(p.value)
        lines.append(f"{p.kind:4} {p.name:12} {p.channel:14} {value}")
    return "\n".join(lines)


def fmt_axis(a: AxisRecord) -> str:
    flags = [f.name or "" for f in PnStatus if a.pn_status & f]
    return (
        f"axis {a.axis:6} #{a.axis_number} pos={a.position_fb:8.2f} cmd={a.position_cmd:8.2f}"
        f" vel={a.velocity_fb:7.2f} [{'|'.join(flags).lower()}] cycle={a.cycle}"
    )


def fmt_diag(d: CycleDiag) -> str:
    def us(x: float) -> str:
        return f"{x * 1e6:8.0f}"

    lines = [
        f"period {d.period_s * 1000:g} ms, {d.cycles} cycles, overruns {d.overruns},"
        f" missed {d.missed_cycles}, window {d.window}",
        f"{'µs':10} {'last':>8} {'p50':>8} {'p99':>8} {'max':>8} {'mean':>8}",
        f"{'execution':10} {us(d.execution.last)} {us(d.execution.p50)} {us(d.execution.p99)}"
        f" {us(d.execution.max)} {us(d.execution.mean)}",
        f"{'jitter':10} {us(d.jitter.last)} {us(d.jitter.p50)} {us(d.jitter.p99)}"
        f" {us(d.jitter.max)} {us(d.jitter.mean)}",
    ]
    if d.watchdog_limit_s is not None:
        lines.append(
            f"stalls     {d.stalls} over the {d.watchdog_limit_s * 1000:g} ms limit"
            f" (longest {d.longest_stall_s * 1000:.0f} ms), {d.watchdog_trips} with an output"
            " on (watchdog trips)"
        )
    if d.events is not None:
        e = d.events
        lines.append(
            f"events     written {e.written}, queued {e.queued}, dropped {e.dropped},"
            f" lost {e.lost}, db {e.file_bytes / 1e6:.1f} MB"
            + (f", last error: {e.last_error}" if e.last_error else "")
        )
    return "\n".join(lines)


def fmt_param(p: ParamValue) -> str:
    flags = (" persisted" if p.persisted else "") + (
        " locked-while-moving" if p.locked_while_moving else ""
    )
    rng = (
        f" [{p.minimum:g}..{p.maximum:g}]"
        if p.minimum is not None and p.maximum is not None
        else ""
    )
    return f"{p.name:32} {p.value!s:>10} {p.unit:6} default {p.default!s}{rng}{flags}"


def fmt_findings(f: Findings) -> str:
    if not f.findings:
        return "ok, no findings"
    return "\n".join(
        f"{x.severity:7} {x.category:14} {x.path or '/':28} {x.message}" for x in f.findings
    )


def fmt_update(u: Update) -> str:
    stamp = time.strftime("%H:%M:%S", time.localtime(u.time))
    if isinstance(u, CycleDiag):
        return f"{stamp} diag\n{fmt_diag(u)}"
    if isinstance(u, Status):
        extra = ""
        if u.session is not None:
            extra = f" revs {u.session.revolutions_done}/{u.session.revolutions_total}"
        if u.fault is not None:
            extra += f" fault {u.fault.code}"
        tilt = "?" if u.tilt_deg is None else f"{u.tilt_deg:.1f}"
        return f"{stamp} status {u.state} tilt={tilt}{extra}"
    if isinstance(u, IoValue):
        return f"{stamp} io {u.kind}/{u.name} = {u.value}"
    if isinstance(u, Completion):
        return f"{stamp} done {fmt_completion(u)}"
    if isinstance(u, CalibrationRecord):
        return f"{stamp} calibration\n{fmt_calibration(u)}"
    return f"{stamp} {fmt_axis(u)}"


def _yn(b: bool) -> str:
    return "yes" if b else "no"


# ------------------------------------------------------------------------------ commands
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


def _parse_value(text: str) -> Any:
    try:
        return json.loads(text)
    except ValueError:
        return text


def run(args: argparse.Namespace, rider: Rider) -> int:  # noqa: C901, PLR0912 - one branch per subcommand
    cmd = args.cmd
    if cmd == "status":
        status = rider.status()
        emit(status, args.json, fmt_status)
    elif cmd == "watch":
        return watch(args, rider)
    elif cmd in ("home", "pause", "resume", "stop", "calibrate", "start"):
        return motion(args, rider)
    elif cmd == "check":
        result: CheckResult = (
            rider.check_calibration() if args.what == "calibration" else rider.check_home()
        )
        emit(
            result,
            args.json,
            lambda r: f"{args.what}: ok={_yn(r.ok)} tilt={_yn(r.tilt)} rotate={_yn(r.rotate)}",
        )
        return EXIT_OK if result.ok else EXIT_REFUSED
    elif cmd == "io":
        points = rider.io()
        emit(points, args.json, fmt_io)
    elif cmd == "axes":
        records = rider.axes()
        emit(records, args.json, lambda rs: "\n".join(fmt_axis(a) for a in rs))
    elif cmd == "diag":
        d = rider.diag(reset=args.reset)
        emit(d, args.json, fmt_diag)
    elif cmd == "params":
        return params(args, rider)
    elif cmd == "validate":
        candidate = None
        if args.config is not None:
            try:
                candidate = args.config.read_bytes()
            except OSError as exc:
                raise UsageError(f"{args.config}: cannot read ({exc.strerror})") from exc
        findings = rider.validate(candidate)
        emit(findings, args.json, fmt_findings)
        return EXIT_OK if findings.ok else EXIT_REFUSED
    elif cmd == "machines":
        return machines(args, rider)
    elif cmd == "done":
        return done(args, rider)
    elif cmd == "calibration":
        return calibration(args, rider)
    elif cmd == "sim":
        return sim(args, rider)
    elif cmd == "events":
        return events(args, rider)
    return EXIT_OK


def motion(args: argparse.Namespace, rider: Rider) -> int:
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


def calibration(args: argparse.Namespace, rider: Rider) -> int:
    """`rider calibration [set …]`: show the values, or enter them by hand."""
    if args.calibration_cmd != "set":
        record = rider.calibration()
        emit(record, args.json, fmt_calibration)
        return EXIT_OK
    try:
        tilt, rotate = _calibration_values(args)
    except ValidationError as exc:
        first = exc.errors(include_url=False)[0]
        raise UsageError(f"calibration value: {first['msg']}") from exc
    record = rider.set_calibration(tilt=tilt, rotate=rotate)
    emit(record, args.json, fmt_calibration)
    return EXIT_OK


def _calibration_values(
    args: argparse.Namespace,
) -> tuple[TiltCalibrationSet | None, RotateCalibrationSet | None]:
    tilt = rotate = None
    if args.tilt_offset is not None or args.tilt_gain is not None:
        if args.tilt_offset is None or args.tilt_gain is None:
            raise UsageError("give both --tilt-offset and --tilt-gain")
        tilt = TiltCalibrationSet(
            offset_counts=args.tilt_offset, gain_counts_per_deg=args.tilt_gain
        )
    if args.rotate_revolution_s is not None or args.rotate_home_arc is not None:
        if args.rotate_revolution_s is None or args.rotate_home_arc is None:
            raise UsageError("give both --rotate-revolution-s and --rotate-home-arc")
        rotate = RotateCalibrationSet(
            revolution_s=args.rotate_revolution_s, home_arc_deg=args.rotate_home_arc
        )
    if tilt is None and rotate is None:
        raise UsageError("give the tilt values, the rotate values, or both")
    return tilt, rotate


def _heartbeat_s(rider: Rider) -> float:
    """The machine's status heartbeat (`Status.heartbeat_s`, which every login may read;
    1 s when the machine does not say)."""
    try:
        return rider.status().heartbeat_s or 1.0
    except RiderError:
        return 1.0


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


def params(args: argparse.Namespace, rider: Rider) -> int:
    sub = args.params_cmd
    if sub == "list":
        values = rider.params()
        emit(values, args.json, lambda vs: "\n".join(fmt_param(p) for p in vs))
        return EXIT_OK
    if sub == "get":
        value = rider.param(args.name)
    elif sub == "set":
        value = rider.set_param(args.name, _parse_value(args.value), persist=args.persist)
    else:
        value = rider.reset_param(args.name)
    emit(value, args.json, fmt_param)
    return EXIT_OK


def machines(args: argparse.Namespace, rider: Rider) -> int:
    found = rider.machines()
    # Followed after the listing, with history (changes against the list are printed): the
    # listing's discovery declares and undeclares a liveliness subscriber on the same key, and
    # zenoh 1.10 (client mode) then stops giving new tokens to one declared before it.
    changes = rider.follow_machines(timeout=0.5, history=True) if args.watch else None
    lines = []
    for m in found:
        up = "?" if m.uptime_s is None else f"{m.uptime_s:.0f} s"
        line = f"{printable(m.id):16} {printable(m.state or '?'):28} up {up}"
        if m.conflict:
            line += f"  CONFLICT: {len(m.sessions)} sessions hold this id"
            line += f" ({printable(', '.join(m.sessions))})"
        lines.append(line)
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


SIM_MAX_ARGS = {"home": 2, "tilt_ai": 2, "stall": 2}
"""Words each `rider sim` fault takes (none for the others)."""


def _tilt_ai_args(words: list[str]) -> tuple[bool, float]:
    """`frozen` and/or a noise amplitude in counts; anything else is a typo, not "no fault"."""
    frozen, noise = False, 0.0
    for word in words:
        if word == "frozen":
            frozen = True
            continue
        try:
            noise = float(word)
        except ValueError:
            noise = math.nan
        if not (math.isfinite(noise) and noise >= 0):
            raise UsageError(f"sim tilt_ai: {word!r} is neither `frozen` nor a noise in counts")
    return frozen, noise


def sim(args: argparse.Namespace, rider: Rider) -> int:
    f, a = args.fault, args.args
    if len(a) > SIM_MAX_ARGS.get(f, 0):
        raise UsageError(f"sim {f}: unexpected {' '.join(a[SIM_MAX_ARGS.get(f, 0) :])!r}")
    if f == "stall" and len(a) > 1 and a[1] not in ("on", "off"):
        raise UsageError(f"sim stall: {a[1]!r} is neither `on` nor `off`")
    try:
        if f == "estop":
            world = rider.sim("estop", pressed=True)
        elif f == "release":
            world = rider.sim("estop", pressed=False)
        elif f == "home":
            stuck = a[1] if len(a) > 1 and a[1] != "none" else None
            world = rider.sim("home", axis=a[0], stuck=stuck)
        elif f == "tilt_ai":
            frozen, noise = _tilt_ai_args(a)
            world = rider.sim("tilt_ai", frozen=frozen, noise_counts=noise)
        elif f == "stall":
            world = rider.sim("stall", axis=a[0], stalled=not (len(a) > 1 and a[1] == "off"))
        else:
            world = rider.sim(f)
    except IndexError as exc:
        raise UsageError(f"sim {f}: missing argument") from exc
    emit(world, args.json, lambda w: w.model_dump_json(indent=2))
    return EXIT_OK


def event_query(args: argparse.Namespace, now: float) -> EventQuery:
    last = args.last
    if last is None and args.since is None and not args.summary:
        last = 20
    try:
        return query_of(args.since, args.until, args.kind, now, last)
    except ValueError as exc:
        raise UsageError(str(exc)) from None


def fmt_event(e: Event, with_machine: bool = False) -> str:
    stamp = datetime.fromtimestamp(e.time).strftime("%Y-%m-%d %H:%M:%S.%f")[:-3]
    who = f"{e.machine_id:8} " if with_machine else ""
    return f"{stamp} {who}#{e.seq:<6} {e.kind:15} {describe(e.details)}"


def fmt_summary(s: EventSummary) -> str:
    faults = ", ".join(f"{code} x{n}" for code, n in s.faults_by_code.items()) or "none"
    rows = [
        ("machine", s.machine_id),
        ("events", str(s.events)),
        (
            "sessions",
            f"{s.sessions_started} started, {s.sessions_done} done, {s.sessions_stopped}"
            f" stopped, {s.sessions_faulted} faulted",
        ),
        ("ride time", f"{s.ride_time_s:.1f} s"),
        ("e-stops", str(s.estops)),
        ("faults", faults),
        ("commands", f"{s.commands} ({s.commands_refused} refused)"),
        ("starts", f"{s.daemon_starts} ({s.unclean_stops} after an unclean stop)"),
    ]
    if s.dropped:
        rows.append(("dropped", f"{s.dropped} events (queue full)"))
    return "\n".join(f"{k:<9}  {v}" for k, v in rows)


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


def main(argv: Sequence[str] | None = None) -> int:  # noqa: C901, PLR0911, PLR0912 - one branch per way the CLI ends (usage, refusal, link, interrupt)
    parser = build_parser()
    args, rest = parser.parse_known_args(argv)
    if args.cmd not in ("fastdata", "ui", "gateway") and rest:
        parser.error(f"unrecognized arguments: {' '.join(rest)}")
    if args.cmd == "fastdata":
        from rider.fastdata import SET_COMMANDS, parse_set
        from rider.fastdata import main as fastdata_main

        if not rest or rest[0] not in SET_COMMANDS:
            return int(fastdata_main(rest))
        # A user register is an online parameter: write it over Zenoh like `params set`.
        reg = parse_set(rest)
        args.cmd, args.params_cmd = "params", "set"
        args.name, args.value, args.persist = reg.name, reg.value, reg.persist
    connect = args.connect or env_connect()
    if args.cmd == "gateway":
        from rider.gateway.cli import main as gateway_main

        return gateway_main(rest, connect, args.zenoh_config, args.zenoh_threads)
    if args.cmd == "ui":
        from rider.ui.app import main as ui_main

        return int(
            ui_main(
                rest,
                connect=connect,
                zenoh_config=args.zenoh_config,
                machine=args.machine,
                zenoh_threads=args.zenoh_threads,
            )
        )
    try:
        # A one-shot command that exits at once supervises nothing; `--wait` and live views do.
        supervise = bool(getattr(args, "wait", False)) or args.cmd == "watch"
        with Rider(
            args.machine,
            supervise=supervise,
            connect=connect,
            zenoh_config_path=args.zenoh_config,
            key_prefix=args.prefix,
            timeout=args.timeout,
            zenoh_threads=args.zenoh_threads,
        ) as rider:
            return run(args, rider)
    except (UsageError, BadCredentials, BadRuntime) as exc:
        print(f"rider: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except CommandRefused as exc:
        if args.json:
            print(exc.reply.model_dump_json())
        print(f"rider: refused: {printable(str(exc))}", file=sys.stderr)
        return EXIT_REFUSED
    except AmbiguousMachine as exc:
        print(f"rider: {exc}", file=sys.stderr)
        return EXIT_AMBIGUOUS
    except LinkLost as exc:
        print(f"rider: {exc}", file=sys.stderr)
        return EXIT_LINK_LOST
    except DuplicateMachine as exc:
        print(f"rider: {printable(str(exc))}", file=sys.stderr)
        return EXIT_DUPLICATE
    except (MachineTimeout, NoMachine) as exc:
        print(f"rider: {exc}", file=sys.stderr)
        return EXIT_NO_REPLY
    except RiderError as exc:
        print(f"rider: {exc}", file=sys.stderr)
        return EXIT_REFUSED
    except KeyboardInterrupt:
        return EXIT_OK
    except BrokenPipeError:
        # `rider … | head`: the reader has gone; stop quietly, and keep the interpreter's own
        # final flush of stdout from raising again.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return EXIT_OK


if __name__ == "__main__":
    sys.exit(main())
