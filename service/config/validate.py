"""The config check: findings `{category, severity, path, message}`, as a soft PLC reports them."""

from __future__ import annotations

import copy
import datetime as dt
import json
import math
from collections.abc import Iterator
from enum import StrEnum
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from hal.iomap import IoMap
from schema.codec import json_pointer
from schema.commands import DEFAULT_SESSION, TiltStep
from schema.findings import Finding, Findings, Severity
from schema.rider import HEARTBEAT_INTERVAL_S
from service.config.model import MIN_SLICE_S, HalBackend, MachineConfig, read_toml

# Below this the wake-up jitter of a Python thread on a general-purpose kernel is of the
# same order as the period itself: the loop runs, but overruns become routine.
MIN_RELIABLE_PERIOD_S = 0.002


class Category(StrEnum):
    """What kind of problem a finding reports; stable strings that scripts may match on."""

    FILE = "file"
    SYNTAX = "syntax"
    UNKNOWN_KEY = "unknown_key"
    MISSING_KEY = "missing_key"
    WRONG_TYPE = "wrong_type"
    OUT_OF_RANGE = "out_of_range"
    IO_CONFLICT = "io_conflict"
    SCAN_PERIOD = "scan_period"
    TIMEOUT = "timeout"
    CALIBRATION = "calibration"
    SUPERVISION = "supervision"
    SIMULATOR = "simulator"
    SESSION = "session"
    BUS = "bus"
    EVENTS = "events"
    HAL = "hal"


_RANGE_TYPES = {
    "greater_than",
    "greater_than_equal",
    "less_than",
    "less_than_equal",
    "finite_number",
    "string_too_short",
    "string_too_long",
    "string_pattern_mismatch",
    "too_short",
    "too_long",
    "enum",
    "literal_error",
}


def _finding(
    severity: Severity, category: Category, path: str, message: str, extra: dict[str, Any]
) -> Finding:
    return Finding(
        category=category.value,
        severity=severity,
        path=path,
        message=message,
        extra={k: _scalar(v) for k, v in extra.items()},
    )


def _error(category: Category, path: str, message: str, **extra: Any) -> Finding:
    return _finding(Severity.ERROR, category, path, message, extra)


def _warning(category: Category, path: str, message: str, **extra: Any) -> Finding:
    return _finding(Severity.WARNING, category, path, message, extra)


def _scalar(value: Any) -> bool | int | float | str | None:
    """A JSON-safe scalar for `Finding.extra` (other values as their short repr)."""
    if value is None or isinstance(value, bool | int | str):
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else str(value)
    return _show(value)


def _schema_findings(exc: ValidationError) -> list[Finding]:
    out = []
    for err in exc.errors(include_url=False):
        kind = err["type"]
        if kind == "extra_forbidden":
            category, message = Category.UNKNOWN_KEY, "unknown key (not part of the machine config)"
        elif kind == "missing":
            category, message = Category.MISSING_KEY, err["msg"]
        elif kind in _RANGE_TYPES:
            category, message = Category.OUT_OF_RANGE, err["msg"]
        else:
            category, message = Category.WRONG_TYPE, err["msg"]
        path = json_pointer(err["loc"])
        limits = {k: v for k, v in (err.get("ctx") or {}).items() if k in _LIMIT_KEYS}
        out.append(
            _error(
                category,
                path,
                f"{message}; got {_show(err.get('input'))}",
                type=kind,
                value=err.get("input"),
                **limits,
            )
        )
    return out


_LIMIT_KEYS = {"gt", "ge", "lt", "le", "min_length", "max_length", "pattern", "expected"}


def _show(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _unrepresentable(data: Any, loc: tuple[str | int, ...] = ()) -> Iterator[Finding]:
    """NaN/±inf slip past one-sided bounds and TOML dates fit no field: report them by path."""
    if isinstance(data, float) and not math.isfinite(data):
        yield _error(
            Category.OUT_OF_RANGE, json_pointer(loc), f"must be a finite number; got {data}"
        )
    elif isinstance(data, dt.date | dt.time):
        yield _error(
            Category.WRONG_TYPE, json_pointer(loc), f"a date/time fits no field; got {data}"
        )
    elif isinstance(data, dict):
        for key, value in data.items():
            yield from _unrepresentable(value, (*loc, str(key)))
    elif isinstance(data, list):
        for i, value in enumerate(data):
            yield from _unrepresentable(value, (*loc, i))


def _as_json(data: dict[str, Any]) -> str:
    # Dates are already reported; None keeps them failing validation at their own path.
    return json.dumps(data, default=lambda _: None, allow_nan=True)


def _io_conflicts(iomap: IoMap) -> Iterator[Finding]:
    channels = iomap.model_dump(by_alias=True, exclude={"estop_active_low"})
    seen: dict[str, str] = {}
    for name, channel in channels.items():
        if channel in seen:
            yield _error(
                Category.IO_CONFLICT,
                f"/hal/iomap/{name}",
                f"channel {channel!r} is already used by {seen[channel]!r}",
                channel=channel,
                used_by=f"/hal/iomap/{seen[channel]}",
            )
        else:
            seen[channel] = name


def _ranges(config: MachineConfig) -> Iterator[Finding]:
    if 0 < config.loop.slice_s < MIN_SLICE_S:
        yield _error(
            Category.OUT_OF_RANGE,
            "/loop/slice_s",
            f"loop.slice_s {config.loop.slice_s:g} is below the shortest slice the kernel"
            f" grants, {MIN_SLICE_S:g} s; 0 keeps the kernel's own",
            value=config.loop.slice_s,
            ge=MIN_SLICE_S,
        )
    tilt = config.tilt
    if tilt.min_deg >= tilt.max_deg:
        yield _error(
            Category.OUT_OF_RANGE,
            "/tilt/min_deg",
            f"tilt.min_deg {tilt.min_deg:g} must be below tilt.max_deg {tilt.max_deg:g}",
            value=tilt.min_deg,
            lt="/tilt/max_deg",
            other=tilt.max_deg,
        )
    if tilt.gain_min_counts_per_deg >= tilt.gain_max_counts_per_deg:
        yield _error(
            Category.OUT_OF_RANGE,
            "/tilt/gain_min_counts_per_deg",
            f"tilt.gain_min_counts_per_deg {tilt.gain_min_counts_per_deg:g} must be below"
            f" tilt.gain_max_counts_per_deg {tilt.gain_max_counts_per_deg:g}",
            value=tilt.gain_min_counts_per_deg,
            lt="/tilt/gain_max_counts_per_deg",
            other=tilt.gain_max_counts_per_deg,
        )


def _scan_period(config: MachineConfig) -> Iterator[Finding]:
    period = config.loop.period_s
    rotate, tilt = config.rotate, config.tilt
    if period < MIN_RELIABLE_PERIOD_S:
        yield _warning(
            Category.SCAN_PERIOD,
            "/loop/period_s",
            f"{period * 1000:g} ms is below the {MIN_RELIABLE_PERIOD_S * 1000:g} ms a Python"
            " scan loop holds reliably: expect overruns (see diag/cycle)",
            value=period,
            ge=MIN_RELIABLE_PERIOD_S,
        )
    # The home switch is only seen if at least one scan falls inside its arc, with margin.
    step = rotate.nominal_speed_dps * period
    if step > rotate.home_arc_deg / 2:
        yield _error(
            Category.SCAN_PERIOD,
            "/loop/period_s",
            f"the rotate axis moves {step:g}° per {period * 1000:g} ms scan, more than half the"
            f" {rotate.home_arc_deg:g}° home-switch arc: the switch can be missed",
            value=period,
            step_deg=step,
            limit_deg=rotate.home_arc_deg / 2,
            other="/rotate/home_arc_deg",
        )
    # The tilt stops on the first scan past its target; a step wider than the settle
    # window overshoots it every time.
    tstep = tilt.nominal_speed_dps * period
    if tstep > 2 * tilt.tolerance_deg:
        yield _error(
            Category.SCAN_PERIOD,
            "/loop/period_s",
            f"the tilt moves {tstep:g}° per scan, more than the ±{tilt.tolerance_deg:g}° settle"
            " window: it cannot settle on a target",
            value=period,
            step_deg=tstep,
            limit_deg=2 * tilt.tolerance_deg,
            other="/tilt/tolerance_deg",
        )
    elif tstep > tilt.tolerance_deg:
        yield _warning(
            Category.SCAN_PERIOD,
            "/loop/period_s",
            f"the tilt moves {tstep:g}° per scan, more than tilt.tolerance_deg"
            f" {tilt.tolerance_deg:g}°: moves will often need corrections",
            value=period,
            step_deg=tstep,
            limit_deg=tilt.tolerance_deg,
            other="/tilt/tolerance_deg",
        )


def _timeouts(config: MachineConfig) -> Iterator[Finding]:
    rotate, tilt = config.rotate, config.tilt
    revolution_s = 360.0 / rotate.nominal_speed_dps
    slowest_s = revolution_s * (1 + rotate.speed_tolerance)
    if rotate.revolution_timeout_s < revolution_s:
        yield _error(
            Category.TIMEOUT,
            "/rotate/revolution_timeout_s",
            f"{rotate.revolution_timeout_s:g} s is shorter than one revolution at"
            f" {rotate.nominal_speed_dps:g}°/s ({revolution_s:.3g} s)",
            value=rotate.revolution_timeout_s,
            ge=revolution_s,
            other="/rotate/nominal_speed_dps",
        )
    elif rotate.revolution_timeout_s < slowest_s:
        yield _warning(
            Category.TIMEOUT,
            "/rotate/revolution_timeout_s",
            f"{rotate.revolution_timeout_s:g} s is shorter than the slowest revolution"
            f" rotate.speed_tolerance accepts ({slowest_s:.3g} s)",
            value=rotate.revolution_timeout_s,
            ge=slowest_s,
            other="/rotate/speed_tolerance",
        )
    leave_s = rotate.home_arc_deg / rotate.nominal_speed_dps
    if rotate.backoff_timeout_s < leave_s:
        yield _error(
            Category.TIMEOUT,
            "/rotate/backoff_timeout_s",
            f"{rotate.backoff_timeout_s:g} s is shorter than crossing the"
            f" {rotate.home_arc_deg:g}° home arc at {rotate.nominal_speed_dps:g}°/s"
            f" ({leave_s:.3g} s)",
            value=rotate.backoff_timeout_s,
            ge=leave_s,
            other="/rotate/home_arc_deg",
        )
    travel_s = (tilt.max_deg - tilt.min_deg) / tilt.nominal_speed_dps
    if travel_s > 0 and tilt.home_timeout_s < travel_s:
        yield _error(
            Category.TIMEOUT,
            "/tilt/home_timeout_s",
            f"{tilt.home_timeout_s:g} s is shorter than the full tilt travel"
            f" {tilt.min_deg:g}°..{tilt.max_deg:g}° at {tilt.nominal_speed_dps:g}°/s"
            f" ({travel_s:.3g} s)",
            value=tilt.home_timeout_s,
            ge=travel_s,
            other="/tilt/nominal_speed_dps",
        )
    if tilt.follow_window_s < config.loop.period_s:
        yield _error(
            Category.TIMEOUT,
            "/tilt/follow_window_s",
            f"{tilt.follow_window_s:g} s is shorter than one scan period"
            f" ({config.loop.period_s:g} s): the position check has nothing to compare",
        )


def _calibration(config: MachineConfig) -> Iterator[Finding]:
    tilt = config.tilt
    stroke_deg = tilt.nominal_speed_dps * tilt.calibration_stroke_s
    span = tilt.max_deg - tilt.min_deg
    if 0 < span < stroke_deg:
        yield _error(
            Category.CALIBRATION,
            "/tilt/calibration_stroke_s",
            f"a {tilt.calibration_stroke_s:g} s stroke at {tilt.nominal_speed_dps:g}°/s drives"
            f" {stroke_deg:g}°, beyond the {span:g}° tilt range",
        )
    # The follow check must see at least `follow_min_counts` even at the lowest plausible gain.
    counts = tilt.nominal_speed_dps * tilt.follow_window_s * tilt.gain_min_counts_per_deg
    if counts < tilt.follow_min_counts:
        yield _warning(
            Category.SUPERVISION,
            "/tilt/follow_min_counts",
            f"at the lowest plausible gain a healthy tilt moves {counts:.3g} counts per"
            f" {tilt.follow_window_s:g} s window, fewer than {tilt.follow_min_counts}:"
            " the follow check may fault a working axis",
        )


def _simulator(config: MachineConfig) -> Iterator[Finding]:
    if config.hal.backend is not HalBackend.SIM:
        return
    sim, rotate, tilt = config.hal.sim, config.rotate, config.tilt
    lo = rotate.nominal_speed_dps * (1 - rotate.speed_tolerance)
    hi = rotate.nominal_speed_dps * (1 + rotate.speed_tolerance)
    if not lo <= sim.rotate_speed_dps <= hi:
        yield _warning(
            Category.SIMULATOR,
            "/hal/sim/rotate_speed_dps",
            f"the simulated rotate axis turns at {sim.rotate_speed_dps:g}°/s, outside"
            f" {lo:g}..{hi:g}°/s that rotate calibration accepts",
        )
    if sim.home_arc_deg < rotate.home_arc_deg:
        yield _warning(
            Category.SIMULATOR,
            "/hal/sim/home_arc_deg",
            f"the simulated home arc {sim.home_arc_deg:g}° is narrower than rotate.home_arc_deg"
            f" {rotate.home_arc_deg:g}° that the scan-period check assumes",
        )
    if sim.tilt_max_deg < tilt.max_deg:
        yield _warning(
            Category.SIMULATOR,
            "/hal/sim/tilt_max_deg",
            f"the simulated tilt stops at {sim.tilt_max_deg:g}°, below tilt.max_deg"
            f" {tilt.max_deg:g}°",
        )


def _session(config: MachineConfig) -> Iterator[Finding]:
    lo, hi = config.tilt.min_deg, config.tilt.max_deg
    if lo >= hi:
        return  # already an error of its own
    for step in DEFAULT_SESSION.steps:
        if isinstance(step, TiltStep) and not lo <= step.degrees <= hi:
            yield _warning(
                Category.SESSION,
                "/tilt/max_deg" if step.degrees > hi else "/tilt/min_deg",
                f"the default session tilts to {step.degrees:g}°, outside"
                f" {lo:g}..{hi:g}°: Start without a session will be refused",
            )


def _bus(config: MachineConfig) -> Iterator[Finding]:
    period = config.loop.period_s
    for name in ("heartbeat_s", "diag_period_s"):
        value = getattr(config.bus, name)
        if value < period:
            yield _warning(
                Category.BUS,
                f"/bus/{name}",
                f"{value:g} s is shorter than the scan period {period:g} s; it cannot be held",
            )


def _rider_loss(config: MachineConfig) -> Iterator[Finding]:
    timeout, period = config.rider_loss.timeout_s, config.loop.period_s
    path = "/rider_loss/timeout_s"
    beat = HEARTBEAT_INTERVAL_S
    if timeout < 2 * beat:
        yield _error(
            Category.SUPERVISION,
            path,
            f"{timeout:g} s is shorter than two Rider heartbeats ({2 * beat:g} s): a healthy"
            " Rider would be judged lost",
        )
    elif timeout < 3 * beat:
        yield _warning(
            Category.SUPERVISION,
            path,
            f"{timeout:g} s leaves room for one late Rider heartbeat ({beat:g} s apart): a"
            " loaded host may pause rides for nothing",
        )
    if timeout < 2 * period:
        yield _error(
            Category.SUPERVISION,
            path,
            f"{timeout:g} s is shorter than two scan periods ({2 * period:g} s): the loop cannot"
            " judge it",
        )


def _events(config: MachineConfig) -> Iterator[Finding]:
    ev = config.events
    if ev.batch_max > ev.queue_capacity:
        yield _warning(
            Category.EVENTS,
            "/events/batch_max",
            f"batch_max {ev.batch_max} is larger than queue_capacity {ev.queue_capacity}:"
            " a batch can never fill",
        )
    if ev.max_age_days < 1:
        yield _warning(
            Category.EVENTS,
            "/events/max_age_days",
            f"{ev.max_age_days:g} days of history cannot answer 'what happened yesterday?'",
        )
    if ev.prune_every_s > ev.max_age_days * 86_400:
        yield _error(
            Category.EVENTS,
            "/events/prune_every_s",
            f"pruning every {ev.prune_every_s:g} s cannot hold a {ev.max_age_days:g}-day retention",
        )


def semantic_findings(config: MachineConfig) -> list[Finding]:
    """Checks across fields that the schema alone cannot express (physics, wiring, timing)."""
    out: list[Finding] = []
    for check in (_io_conflicts(config.hal.iomap), _ranges(config), _scan_period(config)):
        out.extend(check)
    for rule in (_timeouts, _calibration, _simulator, _session, _bus, _rider_loss, _events):
        out.extend(rule(config))
    return out


def findings_of(items: list[Finding]) -> Findings:
    """The report: `ok` is false when any finding is an error."""
    return Findings(ok=not any(f.severity is Severity.ERROR for f in items), findings=items)


def validate_data(data: dict[str, Any]) -> tuple[MachineConfig | None, Findings]:
    """Validate raw config data; the model is None when any error was found."""
    if not isinstance(data, dict):
        return None, findings_of(
            [_error(Category.WRONG_TYPE, "", f"expected a table/object, got {_show(data)}")]
        )
    odd = list(_unrepresentable(data))
    try:
        # Strict JSON mode: a string "0.01" for a float is a mistake to report, not to
        # coerce, while enums still take their string values as a config file spells them.
        config = MachineConfig.model_validate_json(_as_json(data), strict=True)
    except ValidationError as exc:
        # A NaN or a date is reported once, in its own words, not again as a schema error.
        known = {f.path for f in odd}
        found = odd + [f for f in _schema_findings(exc) if f.path not in known]
        return None, findings_of(found + _checks_without(data, found))
    if odd:
        return None, findings_of(odd + _checks_without(data, odd))
    report = findings_of(semantic_findings(config))
    return (config if report.ok else None), report


def _checks_without(data: dict[str, Any], bad: list[Finding]) -> list[Finding]:
    """The cross-field checks with every bad value left at its default, so that one run
    reports every finding; a check on a path already reported is not repeated."""
    repaired = copy.deepcopy(data)
    for f in bad:
        _drop(repaired, f.path)
    try:
        config = MachineConfig.model_validate_json(_as_json(repaired), strict=True)
    except ValidationError:
        return []  # could not isolate the bad values: the schema findings stand alone
    reported = {f.path for f in bad}
    return [f for f in semantic_findings(config) if f.path not in reported]


def _drop(data: dict[str, Any], pointer: str) -> None:
    parts = [p.replace("~1", "/").replace("~0", "~") for p in pointer.split("/")[1:]]
    node: Any = data
    for part in parts[:-1]:
        node = node.get(part) if isinstance(node, dict) else None
    if parts and isinstance(node, dict):
        node.pop(parts[-1], None)


def read_file(path: Path) -> tuple[dict[str, Any] | None, Findings]:
    """The raw TOML of a config file, or None and the one finding that says why not."""
    try:
        return read_toml(path), findings_of([])
    except FileNotFoundError:
        return None, one_error(Category.FILE, f"{path}: no such file")
    except IsADirectoryError:
        return None, one_error(Category.FILE, f"{path}: is a directory")
    except OSError as exc:
        return None, one_error(Category.FILE, f"{path}: cannot read ({exc.strerror})")
    except ValueError as exc:  # tomllib.TOMLDecodeError, UnicodeDecodeError
        return None, one_error(Category.SYNTAX, f"{path}: not valid TOML: {exc}")


def one_error(category: Category, message: str, path: str = "") -> Findings:
    """A report of one error (a file that cannot be read, a backend that cannot open)."""
    return findings_of([_error(category, path, message)])


def hardware_findings(config: MachineConfig) -> list[Finding]:
    """What the chosen backend finds on this host (piCtory config, process image, IO names).

    Not part of `validate_data`: it reads files of the host, and `--hal` may pick another
    backend than the file does. `machine validate` adds it to the report; `machine run` and
    `machine supervise` run it (on the config with their overrides) before they start.
    """
    if config.hal.backend is not HalBackend.REVPI:
        return []
    from hal.revpi import check_revpi_io  # only with that backend: it pulls in revpimodio2

    revpi = config.hal.revpi
    return check_revpi_io(config.hal.iomap, revpi.configrsc, revpi.procimg)


def finding_line(source: str, f: Finding) -> str:
    """One finding as `machine run`, `supervise` and the config loader print it on stderr."""
    return f"{source}: {f.severity}: {f.category} at {f.path or '/'}: {f.message}"
