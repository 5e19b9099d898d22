"""The config check's rules across fields: what the schema alone cannot say (wiring, timing,
physics, the simulator, the default session, retention)."""

from __future__ import annotations

from collections.abc import Iterator

from pydantic import BaseModel

from ride_machine.hal.iomap import IoMap
from ride_machine.schema.commands import DEFAULT_SESSION, TiltStep
from ride_machine.schema.findings import Finding
from ride_machine.schema.rider import HEARTBEAT_INTERVAL_S

from .model import MIN_SLICE_S, HalBackend, MachineConfig
from .report import Category, error, warning

# Below this the wake-up jitter of a Python thread on a general-purpose kernel is of the
# same order as the period itself: the loop runs, but overruns become routine.
MIN_RELIABLE_PERIOD_S = 0.002
GAIN_BAND_MAX = 0.10
"""The widest tilt gain band (± of its middle) the check takes without a warning."""


def _io_conflicts(iomap: IoMap) -> Iterator[Finding]:
    channels = iomap.model_dump(by_alias=True, exclude={"estop_active_low"})
    seen: dict[str, str] = {}
    for name, channel in channels.items():
        if channel is None:  # an optional point left unmapped
            continue
        if channel in seen:
            yield error(
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
        yield error(
            Category.OUT_OF_RANGE,
            "/loop/slice_s",
            f"loop.slice_s {config.loop.slice_s:g} is below the shortest slice the kernel"
            f" grants, {MIN_SLICE_S:g} s; 0 keeps the kernel's own",
            value=config.loop.slice_s,
            ge=MIN_SLICE_S,
        )
    for low, high in (
        ("min_deg", "max_deg"),
        ("gain_min_counts_per_deg", "gain_max_counts_per_deg"),
        ("zero_min_counts", "zero_max_counts"),
    ):
        yield from _below(config.tilt, "tilt", low, high)


def _below(section: BaseModel, name: str, low: str, high: str) -> Iterator[Finding]:
    """`low` must be below `high` (a range of `section`, `[name]`), or an error at `low`."""
    lo, hi = getattr(section, low), getattr(section, high)
    if lo >= hi:
        yield error(
            Category.OUT_OF_RANGE,
            f"/{name}/{low}",
            f"{name}.{low} {lo:g} must be below {name}.{high} {hi:g}",
            value=lo,
            lt=f"/{name}/{high}",
            other=hi,
        )


def _scan_period(config: MachineConfig) -> Iterator[Finding]:
    period = config.loop.period_s
    rotate, tilt = config.rotate, config.tilt
    if period < MIN_RELIABLE_PERIOD_S:
        yield warning(
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
        yield error(
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
        yield error(
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
        yield warning(
            Category.SCAN_PERIOD,
            "/loop/period_s",
            f"the tilt moves {tstep:g}° per scan, more than tilt.tolerance_deg"
            f" {tilt.tolerance_deg:g}°: moves will often need corrections",
            value=period,
            step_deg=tstep,
            limit_deg=tilt.tolerance_deg,
            other="/tilt/tolerance_deg",
        )


def _watchdog_reach(config: MachineConfig) -> Iterator[Finding]:
    """A stalled scan leaves the relays as they were until the watchdog drops them: the rotate
    may turn that far unseen. Past its whole arc a home edge can pass between two scans; the
    revolution is then found late (ROTATE_HOME_TIMEOUT), not counted wrong, but it stops."""
    rotate, limit = config.rotate, config.loop.watchdog_limit_s
    step = rotate.nominal_speed_dps * config.loop.period_s
    unseen = rotate.nominal_speed_dps * limit
    # Once: a scan too slow for the arc is `_scan_period`'s error already.
    if step <= rotate.home_arc_deg / 2 and unseen > rotate.home_arc_deg:
        yield warning(
            Category.SCAN_PERIOD,
            "/loop/watchdog_periods",
            f"a scan stalled up to the {limit:g} s watchdog limit lets the rotate turn"
            f" {unseen:g}° with its relay on, more than its {rotate.home_arc_deg:g}° home arc:"
            " a stall can hide a home edge, and the ride then stops with ROTATE_HOME_TIMEOUT",
            value=limit,
            travel_deg=unseen,
            limit_deg=rotate.home_arc_deg,
            other="/rotate/home_arc_deg",
        )


def _timeouts(config: MachineConfig) -> Iterator[Finding]:
    rotate, tilt = config.rotate, config.tilt
    revolution_s = 360.0 / rotate.nominal_speed_dps
    slowest_s = revolution_s * (1 + rotate.speed_tolerance)
    if rotate.revolution_timeout_s < revolution_s:
        yield error(
            Category.TIMEOUT,
            "/rotate/revolution_timeout_s",
            f"{rotate.revolution_timeout_s:g} s is shorter than one revolution at"
            f" {rotate.nominal_speed_dps:g}°/s ({revolution_s:.3g} s)",
            value=rotate.revolution_timeout_s,
            ge=revolution_s,
            other="/rotate/nominal_speed_dps",
        )
    elif rotate.revolution_timeout_s < slowest_s:
        yield warning(
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
        yield error(
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
        yield error(
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
        yield error(
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
        yield error(
            Category.CALIBRATION,
            "/tilt/calibration_stroke_s",
            f"a {tilt.calibration_stroke_s:g} s stroke at {tilt.nominal_speed_dps:g}°/s drives"
            f" {stroke_deg:g}°, beyond the {span:g}° tilt range",
        )
    # The band is the one bound on a calibration that the drive's speed cannot fool: a wide
    # one lets a drive off its nominal speed calibrate (and ride) off by as much.
    lo, hi = tilt.gain_min_counts_per_deg, tilt.gain_max_counts_per_deg
    if lo < hi and (hi - lo) / (hi + lo) > GAIN_BAND_MAX:
        far = max(abs(tilt.min_deg), abs(tilt.max_deg))
        yield warning(
            Category.CALIBRATION,
            "/tilt/gain_min_counts_per_deg",
            f"the tilt sensor's gain band {lo:g}..{hi:g} counts/° is wider than"
            f" ±{GAIN_BAND_MAX * 100:g} %: a calibration off by up to"
            f" {(hi - lo) / lo * 100:.0f} % passes it, {far * (hi - lo) / lo:.3g}° at {far:g}°;"
            " set it from the sensor's datasheet",
        )
    # A latch may be `latch_tolerance_deg` off each time: a zero band narrower than two of
    # them (in degrees even at the lowest gain) refuses good calibrations now and then.
    half_deg = (tilt.zero_max_counts - tilt.zero_min_counts) / (2 * lo)
    if lo < hi and 0 < half_deg < 2 * tilt.latch_tolerance_deg:
        yield warning(
            Category.CALIBRATION,
            "/tilt/zero_min_counts",
            f"the tilt zero band is ±{half_deg:.2g}° wide, less than twice"
            f" tilt.latch_tolerance_deg {tilt.latch_tolerance_deg:g}°: a good calibration whose"
            " latch falls at the edge of its tolerance may be refused",
        )
    # The follow check must see at least `follow_min_counts` even at the lowest plausible gain.
    counts = tilt.nominal_speed_dps * tilt.follow_window_s * tilt.gain_min_counts_per_deg
    if counts < tilt.follow_min_counts:
        yield warning(
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
        yield warning(
            Category.SIMULATOR,
            "/hal/sim/rotate_speed_dps",
            f"the simulated rotate axis turns at {sim.rotate_speed_dps:g}°/s, outside"
            f" {lo:g}..{hi:g}°/s that rotate calibration accepts",
        )
    if sim.home_arc_deg < rotate.home_arc_deg:
        yield warning(
            Category.SIMULATOR,
            "/hal/sim/home_arc_deg",
            f"the simulated home arc {sim.home_arc_deg:g}° is narrower than rotate.home_arc_deg"
            f" {rotate.home_arc_deg:g}° that the scan-period check assumes",
        )
    measured = sim.ai_gain_counts_per_deg * sim.tilt_speed_dps / tilt.nominal_speed_dps
    lo, hi = tilt.gain_min_counts_per_deg, tilt.gain_max_counts_per_deg
    if lo < hi and not lo <= measured <= hi:  # an inverted band is an error of its own
        yield warning(
            Category.SIMULATOR,
            "/hal/sim/ai_gain_counts_per_deg",
            f"the simulated tilt ({sim.ai_gain_counts_per_deg:g} counts/° at"
            f" {sim.tilt_speed_dps:g}°/s) calibrates to {measured:.3g} counts/°, outside"
            f" tilt.gain_min..max_counts_per_deg {tilt.gain_min_counts_per_deg:g}.."
            f"{tilt.gain_max_counts_per_deg:g}: CalibrateTilt will refuse it",
        )
    zero = sim.ai_offset_counts + sim.ai_gain_counts_per_deg * sim.tilt_home_deg
    bottom, top = tilt.zero_min_counts, tilt.zero_max_counts
    if bottom < top and not bottom <= zero <= top:
        yield warning(
            Category.SIMULATOR,
            "/hal/sim/ai_offset_counts",
            f"the simulated tilt reads {zero:g} counts at its home switch, outside"
            f" tilt.zero_min..max_counts {tilt.zero_min_counts:g}..{tilt.zero_max_counts:g}:"
            " CalibrateTilt will refuse its zero",
        )
    if sim.tilt_max_deg < tilt.max_deg:
        yield warning(
            Category.SIMULATOR,
            "/hal/sim/tilt_max_deg",
            f"the simulated tilt stops at {sim.tilt_max_deg:g}°, below tilt.max_deg"
            f" {tilt.max_deg:g}°",
        )


def _charge_pump(config: MachineConfig) -> Iterator[Finding]:
    """Only a charge pump survives the whole controller stopping (docs/revpi.md): a RevPi
    without one is told so; a simulated relay the scan cannot hold, or that a stall the
    watchdog tolerates would drop, is said."""
    hal, loop = config.hal, config.loop
    if hal.iomap.charge_pump is None:
        if hal.backend is HalBackend.REVPI:
            yield warning(
                Category.SUPERVISION,
                "/hal/iomap/chargePump",
                "no charge pump: when the whole controller stops (a hung host, a paused"
                " container, a frozen kernel) nothing takes the drives' power away but the"
                " RevPi's own 60 s watchdog, if armed; wire a digital output to an external"
                " watchdog relay in the drives' power and map it (docs/revpi.md)",
            )
        return
    if hal.backend is not HalBackend.SIM:
        return
    timeout, limit = hal.sim.charge_pump_timeout_s, loop.watchdog_limit_s
    if timeout < 2 * loop.period_s:
        yield error(
            Category.SIMULATOR,
            "/hal/sim/charge_pump_timeout_s",
            f"the charge pump changes level once a scan ({loop.period_s:g} s): a relay that"
            f" drops {timeout:g} s after the last change cannot be held (at least two periods)",
        )
    elif timeout < limit:
        yield warning(
            Category.SIMULATOR,
            "/hal/sim/charge_pump_timeout_s",
            f"the simulated charge-pump relay drops the drives {timeout:g} s after the scan"
            f" stops, before the {limit:g} s watchdog limit: a stall the watchdog tolerates"
            " cuts the drives without a fault",
        )


def _session(config: MachineConfig) -> Iterator[Finding]:
    lo, hi = config.tilt.min_deg, config.tilt.max_deg
    if lo >= hi:
        return  # already an error of its own
    for step in DEFAULT_SESSION.steps:
        if isinstance(step, TiltStep) and not lo <= step.degrees <= hi:
            yield warning(
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
            yield warning(
                Category.BUS,
                f"/bus/{name}",
                f"{value:g} s is shorter than the scan period {period:g} s; it cannot be held",
            )


def _rider_loss(config: MachineConfig) -> Iterator[Finding]:
    timeout, period = config.rider_loss.timeout_s, config.loop.period_s
    path = "/rider_loss/timeout_s"
    beat = HEARTBEAT_INTERVAL_S
    if timeout < 2 * beat:
        yield error(
            Category.SUPERVISION,
            path,
            f"{timeout:g} s is shorter than two Rider heartbeats ({2 * beat:g} s): a healthy"
            " Rider would be judged lost",
        )
    elif timeout < 3 * beat:
        yield warning(
            Category.SUPERVISION,
            path,
            f"{timeout:g} s leaves room for one late Rider heartbeat ({beat:g} s apart): a"
            " loaded host may pause rides for nothing",
        )
    if timeout < 2 * period:
        yield error(
            Category.SUPERVISION,
            path,
            f"{timeout:g} s is shorter than two scan periods ({2 * period:g} s): the loop cannot"
            " judge it",
        )


def _events(config: MachineConfig) -> Iterator[Finding]:
    ev = config.events
    if ev.batch_max > ev.queue_capacity:
        yield warning(
            Category.EVENTS,
            "/events/batch_max",
            f"batch_max {ev.batch_max} is larger than queue_capacity {ev.queue_capacity}:"
            " a batch can never fill",
        )
    if ev.max_age_days < 1:
        yield warning(
            Category.EVENTS,
            "/events/max_age_days",
            f"{ev.max_age_days:g} days of history cannot answer 'what happened yesterday?'",
        )
    if ev.prune_every_s > ev.max_age_days * 86_400:
        yield error(
            Category.EVENTS,
            "/events/prune_every_s",
            f"pruning every {ev.prune_every_s:g} s cannot hold a {ev.max_age_days:g}-day retention",
        )


def semantic_findings(config: MachineConfig) -> list[Finding]:
    """Checks across fields that the schema alone cannot express (physics, wiring, timing)."""
    out: list[Finding] = []
    for check in (_io_conflicts(config.hal.iomap), _ranges(config), _scan_period(config)):
        out.extend(check)
    for rule in (
        _watchdog_reach,
        _timeouts,
        _calibration,
        _simulator,
        _charge_pump,
        _session,
        _bus,
        _rider_loss,
        _events,
    ):
        out.extend(rule(config))
    return out
