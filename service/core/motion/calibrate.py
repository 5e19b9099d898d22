"""Calibration: each axis measures its reference at least twice and refuses when they disagree.

The tilt latches its zero (the home switch's closing edge, approached from above) before and
after a stroke up whose analog speed gives the gain; the two zeros must agree within
`tilt.repeat_tolerance_deg`. The rotate, once homed, turns (two revolutions or more) and times
the revolution from its closing edges and from its opening edges; the two must agree within
`rotate.repeat_tolerance_deg` of travel. Either refusal is `CALIBRATION_NOT_REPEATABLE`, with
both values in the reason, never DONE. docs/homing.md has the sequences.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable
from enum import Enum, auto
from itertools import pairwise

from ride_machine.schema.commands import Direction
from ride_machine.schema.status import FaultCode
from ride_machine.service.config.axes import RotateSection, TiltSection

from .base import REVERSE_DWELL_S, Measurement, Step
from .devices import (
    RotateAxis,
    RotateCalibration,
    TiltAxis,
    TiltCalibration,
    TiltDirection,
)
from .homing import Latch, OnSwitch, RotateHome, TiltApproach
from .plausibility import TiltSupervisor
from .scale import gain_problem, zero_problem
from .witness import half_travel, judge_entered, line


class TiltCalPhase(Enum):
    FIRST = auto()
    """Latch the zero (the home edge, from above)."""
    REST = auto()
    """Relay off before reversing."""
    STROKE = auto()
    """Drive up for `calibration_stroke_s`; the gain from the analog's speed meanwhile."""
    SECOND = auto()
    """Latch the zero again, coming down from the top."""


class TiltCalibrate(Measurement[TiltAxis, TiltSection]):
    """Latch the zero, a stroke up at the nominal speed (the gain: the analog's speed on the
    line through the stroke's samples, over the nominal speed), latch the zero again: the
    offset is the mean of the two latches, which must agree. It ends at home.

    The gain is the slope of samples stamped with their scan's time, not the travel over a
    timed stroke: a scan stalled before it writes the relay on or off lengthens or shortens
    the stroke by the stall, not the speed."""

    axis_name = "tilt"
    target_deg = 0.0

    def __init__(self, axis: TiltAxis, cfg: TiltSection) -> None:
        super().__init__(axis, cfg)
        self.phase = TiltCalPhase.FIRST
        self.homing: TiltApproach | None = TiltApproach(axis, cfg)
        self.zeros: list[Latch] = []
        self._samples: list[tuple[float, int]] = []
        self._gain = 0.0
        self._sup = TiltSupervisor(axis, cfg)
        self.result: TiltCalibration | None = None
        # Measure uncalibrated; a failed calibration puts the previous one back.
        self._previous, axis.calibration = axis.calibration, None

    def update(self, now: float) -> Step:
        step = self._measure(now)
        if step is Step.FAULT and self.result is None:
            self.axis.calibration = self._previous
        return step

    def _measure(self, now: float) -> Step:
        if self.homing is not None:  # FIRST or SECOND
            step = self._step(self.homing, now)
            if step is not Step.DONE:
                return step
            assert self.homing.latch is not None
            self.zeros.append(self.homing.latch)
            self.homing = None
            if self.phase is TiltCalPhase.SECOND:
                return self._compute()
            self.phase = TiltCalPhase.REST
            self.timer.start(now, REVERSE_DWELL_S)
        if self.phase is TiltCalPhase.REST:
            if not self.timer.done(now):
                return Step.BUSY
            self.phase, self._samples = TiltCalPhase.STROKE, []
            self.timer.start(now, self.cfg.calibration_stroke_s)
            self._sup.reset()
            self.axis.drive(TiltDirection.UP)  # its scan was at rest: not a sample
            return Step.BUSY
        return self._stroke(now)

    def _stroke(self, now: float) -> Step:
        self._samples.append((now, self.axis.read_raw()))  # moving since the write before
        if self.timer.done(now):
            self.axis.stop()
            return self._top()
        fault = self._sup.drive(now, TiltDirection.UP)
        return Step.BUSY if fault is None else self._fault(fault)

    def _top(self) -> Step:
        """The gain from the stroke, checked; then down to latch the zero again."""
        cfg = self.cfg
        n = len(self._samples)
        gain = line(self._samples)[2] / cfg.nominal_speed_dps
        if n < cfg.calibration_samples:  # a sample each scan: the scan stalled, not the sensor
            return self._fail(
                FaultCode.CALIBRATION_NOT_REPEATABLE,
                f"tilt stroke of {cfg.calibration_stroke_s:g} s measured in {n} scans, fewer than"
                f" {cfg.calibration_samples}: the scan stalled during it (a loaded host);"
                " calibrate again",
            )
        outside = gain_problem(gain, cfg)
        if outside is not None:
            return self._fail(
                FaultCode.CALIBRATION_IMPLAUSIBLE, f"{outside.message}; from {n} samples"
            )
        if self.axis.is_home():
            stroke_deg = cfg.nominal_speed_dps * cfg.calibration_stroke_s
            return self._fail(
                FaultCode.TILT_HOME_STUCK,
                f"tilt home switch still closed {stroke_deg:.1f}° above home (stuck closed)",
            )
        self._gain = gain
        self.phase = TiltCalPhase.SECOND
        self.homing = TiltApproach(self.axis, self.cfg, rest_s=REVERSE_DWELL_S)
        return Step.BUSY

    def _compute(self) -> Step:
        first, second = (z.raw for z in self.zeros)
        assert first is not None and second is not None
        apart = abs(first - second) / self._gain
        tol = self.cfg.repeat_tolerance_deg
        if apart > tol:
            return self._fail(
                FaultCode.CALIBRATION_NOT_REPEATABLE,
                f"tilt zero latched at {first:.1f} and then {second:.1f} counts, {apart:.2f}°"
                f" apart (gain {self._gain:.2f} counts/°); they must agree within {tol:g}°"
                " (a bouncing or loose home switch, or a noisy sensor)",
            )
        outside = zero_problem((first + second) / 2, self.cfg)
        if outside is not None:
            return self._fail(FaultCode.CALIBRATION_IMPLAUSIBLE, outside.message)
        return self._finish((first + second) / 2)

    def _finish(self, offset: float) -> Step:
        """Both zeros agree on `offset`: the result, in use from now on."""
        self.result = TiltCalibration(offset_counts=offset, gain_counts_per_deg=self._gain)
        self.axis.calibration = self.result
        return Step.DONE

    def abandon(self) -> None:
        self.halt()
        if self.result is None:
            self.axis.calibration = self._previous

    def _start_over(self) -> None:
        # An interrupted stroke measures nothing: start over with the first latch.
        self.phase, self.zeros = TiltCalPhase.FIRST, []
        self.homing = TiltApproach(self.axis, self.cfg, rest_s=REVERSE_DWELL_S)


class TiltVerify(TiltCalibrate):
    """A calibration entered by hand, verified before a session may run on it: the measurement
    of `TiltCalibrate` (a zero, a stroke up, the zero again), judged against the entered values
    instead of replacing them (`judge_entered`). It ends at home with the calibration verified,
    or in the fault of the witness that disagrees (the entered values stay, unverified)."""

    def __init__(self, axis: TiltAxis, cfg: TiltSection) -> None:
        super().__init__(axis, cfg)
        # Measured through the entered values: the speed checks stop a gross error within a
        # speed window (`TiltSupervisor`), before the stroke is over.
        axis.calibration = self._previous

    def _finish(self, offset: float) -> Step:
        entered = self._previous
        assert entered is not None, "only an entered calibration is verified"
        fault = judge_entered(entered, offset, self._gain, self.cfg)
        if fault is not None:
            return self._fault(fault)
        self.result = dataclasses.replace(entered, verified=True)
        self.axis.calibration = self.result
        return Step.DONE


class RotateCalibrate(Measurement[RotateAxis, RotateSection]):
    """Home, then turn CW and time the revolution twice — closing edge to closing edge and
    opening edge to opening edge — from edges latched within `latch_tolerance_deg`, and the
    arc the switch stays closed (a closing edge to the next opening). An edge seen across a
    stall is not used: the turning goes on until each of the three has a pair of good edges,
    `latch_attempts` revolutions more at most. It ends on a good closing edge (home)."""

    axis_name = "rotate"
    target_deg = 0.0

    def __init__(self, axis: RotateAxis, cfg: RotateSection) -> None:
        super().__init__(axis, cfg)
        self.homing: RotateHome | None = RotateHome(axis, cfg)
        self.edges: list[tuple[bool, Latch]] = []
        """(closing, latch) of each switch edge passed since homing."""
        self._last: tuple[float, bool] | None = None
        self.result: RotateCalibration | None = None
        self.stopped: OnSwitch | None = None
        """Measured and stopped on a closing edge, until a later scan reads the switch closed."""

    def update(self, now: float) -> Step:
        if self.homing is not None:
            step = self._step(self.homing, now)
            if step is not Step.DONE:
                return step
            self.homing = None
            if self.result is not None:  # measured, and back on the switch it ran past
                return Step.DONE
            self.timer.start(now, self.cfg.revolution_timeout_s)
        home = self.axis.is_home()
        if self.stopped is not None:
            return self._on_switch(now, home)
        last, self._last = self._last, (now, home)
        if last is not None and home != last[1]:
            speed = self.cfg.nominal_speed_dps
            self.edges.append((home, Latch(last[0], now, half_travel(speed, last[0], now))))
            if home:
                self.timer.start(now)
                measured = self._measured()
                if measured is Step.DONE:
                    self.axis.stop()
                    self.stopped = OnSwitch(now)
                    return Step.BUSY
                if measured is not None:
                    return measured
        if self.timer.expired(now):
            return self._fail(
                FaultCode.ROTATE_HOME_TIMEOUT,
                f"rotate home switch not seen within {self.cfg.revolution_timeout_s:g} s"
                " while measuring a revolution",
            )
        self.axis.drive(Direction.CW)
        return Step.BUSY

    def _on_switch(self, now: float, home: bool) -> Step:
        """It ends on the switch: a stop written late ran past it (`OnSwitch`), and the rotate
        is homed again, back through the switch, keeping what it measured."""
        assert self.stopped is not None
        step = self.stopped.step(now, home)
        if step is not None:
            return step
        self.stopped, self.homing = None, RotateHome(self.axis, self.cfg)
        self.homing.behind = True
        return Step.BUSY

    def _good(self, latch: Latch) -> bool:
        return latch.half_deg <= self.cfg.latch_tolerance_deg

    def _pairs(self) -> tuple[Latch, Latch, Latch, Latch, Latch, Latch] | None:
        """The latest well-latched (closing, closing), (opening, opening) one revolution apart
        and (closing, next opening); None while one of them is missing."""
        edges = self.edges
        by_closing = self._latest(pairwise(e for c, e in edges if c))
        by_opening = self._latest(pairwise(e for c, e in edges if not c))
        arc = self._latest((a, b) for (ca, a), (cb, b) in pairwise(edges) if ca and not cb)
        if by_closing is None or by_opening is None or arc is None:
            return None
        return (*by_closing, *by_opening, *arc)

    def _latest(self, pairs: Iterable[tuple[Latch, Latch]]) -> tuple[Latch, Latch] | None:
        good = [(a, b) for a, b in pairs if self._good(a) and self._good(b)]
        return good[-1] if good else None

    def _measured(self) -> Step | None:
        """At a closing edge: the result, once measured and this edge is a good one to stop
        on; None: turn on."""
        pairs = self._pairs()
        if pairs is not None and self._good(self.edges[-1][1]):
            return self._finish(*pairs)
        closings = sum(1 for closing, _ in self.edges if closing)
        if closings >= 2 + self.cfg.latch_attempts:
            tol = self.cfg.latch_tolerance_deg
            worst = max(e.half_deg for _, e in self.edges)
            return self._fail(
                FaultCode.HOME_EDGE_UNCERTAIN,
                f"rotate switch edges not latched within ±{tol:g}° in {closings} revolutions"
                f" (worst ±{worst:.2f}°: a loaded host stalling the scan, or a bouncing switch)",
            )
        return None

    def _finish(
        self, close1: Latch, close2: Latch, open1: Latch, open2: Latch, arc0: Latch, arc1: Latch
    ) -> Step:
        by_closing, by_opening = close2.at - close1.at, open2.at - open1.at
        revolution_s = (by_closing + by_opening) / 2
        nominal_s = 360.0 / self.cfg.nominal_speed_dps
        tol = self.cfg.speed_tolerance
        if not nominal_s * (1 - tol) <= revolution_s <= nominal_s * (1 + tol):
            return self._fail(
                FaultCode.CALIBRATION_IMPLAUSIBLE,
                f"one revolution took {revolution_s:.3f} s; expected {nominal_s:.3f} s"
                f" ± {tol:.0%} from rotate.nominal_speed_dps",
            )
        apart = abs(by_closing - by_opening) / revolution_s * 360.0
        if apart > self.cfg.repeat_tolerance_deg:
            return self._fail(
                FaultCode.CALIBRATION_NOT_REPEATABLE,
                f"rotate revolution timed {by_closing:.3f} s between closing edges and"
                f" {by_opening:.3f} s between opening edges, {apart:.2f}° of travel apart;"
                f" they must agree within {self.cfg.repeat_tolerance_deg:g}°",
            )
        arc = (arc1.at - arc0.at) / revolution_s * 360.0
        self.result = RotateCalibration(revolution_s=revolution_s, home_arc_deg=arc)
        return Step.DONE

    def _start_over(self) -> None:
        self.homing, self.edges, self._last = RotateHome(self.axis, self.cfg), [], None
