"""How the `rider` command prints what the machine sent: JSON as sent (`--json`), or a table
or line per record with every wire string made printable (`emit`)."""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from datetime import datetime
from typing import TYPE_CHECKING, TypeVar

from pydantic import BaseModel

from ride_machine.schema.axes import AxisRecord, PnStatus
from ride_machine.schema.calibration import CalibrationRecord
from ride_machine.schema.commands import CheckResult, Reply
from ride_machine.schema.completion import Completion
from ride_machine.schema.diag import CycleDiag
from ride_machine.schema.findings import Findings
from ride_machine.schema.io import IoValue
from ride_machine.schema.params import ParamValue
from ride_machine.schema.sim import SimWorldState
from ride_machine.schema.status import Status

from .machines import MachineInfo
from .replies import Update
from .text import printable, shown

if TYPE_CHECKING:
    from ride_machine.common.event_summary import EventSummary
    from ride_machine.schema.events import Event

T = TypeVar("T")


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
        ("calibrated", f"tilt={yn(s.calibrated.tilt)} rotate={yn(s.calibrated.rotate)}"),
        ("home", f"tilt={yn(s.homed.tilt)} rotate={yn(s.homed.rotate)}"),
        ("e-stop", f"active={yn(s.estop.active)} latched={yn(s.estop.latched)}"),
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
        line += f" ok={yn(r.result.ok)} tilt={yn(r.result.tilt)} rotate={yn(r.result.rotate)}"
    return line


def fmt_check(what: str, r: CheckResult) -> str:
    return f"{what}: ok={yn(r.ok)} tilt={yn(r.tilt)} rotate={yn(r.rotate)}"


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
        + (" NOT VERIFIED: the next Home verifies it" if t.verified is False else "")
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


def fmt_sim_world(w: SimWorldState) -> str:
    """The simulated world in a few lines (`--json` gives every field)."""

    def switch(closed: bool | None) -> str:
        return "" if closed is None else f", home switch {'closed' if closed else 'open'}"

    if w.drives_powered is None:
        drives = "no charge pump"
    else:
        drives = "drives powered" if w.drives_powered else f"drives off {w.drives_off_s or 0:.1f} s"
    on = sorted(name for name, closed in w.relays.items() if closed)
    rows = [
        ("world", f"E-stop {'pressed' if w.estop_pressed else 'released'}, {drives}"),
        ("tilt", f"{w.tilt_deg:.1f}°{switch(w.tilt_home_closed)}"),
        ("rotate", f"{w.rotate_deg:.1f}° ({w.revolutions:.2f} rev){switch(w.rotate_home_closed)}"),
        ("relays", ", ".join(on) + " on" if on else "all off"),
        ("faults", ", ".join(f"{k}={v}" for k, v in sorted(w.faults.items())) or "none"),
    ]
    if w.late_steps is not None:
        rows.append(("late", f"{w.late_steps} steps, longest {w.longest_late_s or 0:.3f} s"))
    return "\n".join(f"{k:<9}  {v}" for k, v in rows)


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


def fmt_machine(m: MachineInfo) -> str:
    """One line of `rider machines` (its id and state as the wire gave them, made printable)."""
    up = "?" if m.uptime_s is None else f"{m.uptime_s:.0f} s"
    line = f"{printable(m.id):16} {printable(m.state or '?'):28} up {up}"
    if m.conflict:
        line += f"  CONFLICT: {len(m.sessions)} sessions hold this id"
        line += f" ({printable(', '.join(m.sessions))})"
    return line


def fmt_event(e: Event, with_machine: bool = False) -> str:
    from ride_machine.common.event_words import describe

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


def yn(b: bool) -> str:
    return "yes" if b else "no"
