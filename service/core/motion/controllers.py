"""The motions of a session: the tilt to an angle, the rotate N revolutions, and the session as a
chain of them. The building blocks are in `service.core.motion.base`, homing and calibration in
`service.core.motion.homing` and `service.core.motion.calibrate`, the checks while moving in
`service.core.motion.plausibility`.
"""

from __future__ import annotations

from collections.abc import Callable

from ride_machine.schema.commands import Direction, RotateStep, Session, TiltStep
from ride_machine.schema.status import FaultCode, SessionProgress
from ride_machine.service.config.axes import RotateSection, TiltSection
from ride_machine.service.config.model import MachineConfig

from .base import REVERSE_DWELL_S, AxisController, Chain, Controller, Step
from .devices import Devices, RotateAxis, RotateCalibration, TiltAxis, TiltDirection
from .homing import OnSwitch, RotateHome
from .plausibility import RevolutionCheck, TiltSupervisor
from .witness import ZeroWitness, half_travel, off_zero


class TiltMove(AxisController[TiltAxis, TiltSection]):
    """Drive to an absolute angle (bang-bang on the relay), then check it settled in tolerance."""

    axis_name = "tilt"
    MAX_CORRECTIONS = 3

    def __init__(self, axis: TiltAxis, cfg: TiltSection, target_deg: float) -> None:
        super().__init__(axis, cfg)
        self.target = self.target_deg = target_deg
        self._sup = TiltSupervisor(axis, cfg)
        self._zero = ZeroWitness(cfg)
        self._dir: TiltDirection | None = None
        self._corrections = 0

    def update(self, now: float) -> Step:
        pos = self.axis.read_position_degrees()
        if pos is None:
            return self._fail(FaultCode.TILT_TIMEOUT, "tilt is not calibrated")
        err = self.target - pos
        if not self.timer.started:  # armed from the distance left
            travel_s = abs(err) / self.cfg.nominal_speed_dps
            self.timer.start(now, 1.5 * travel_s + self.cfg.move_timeout_margin_s)
        failed = self._stuck(now, pos)
        if failed is not None:
            return failed
        if self._dir is None:  # stopped: settled, or correct an overshoot
            settled = self._settle(err)
            if settled is not None:
                return settled
        return self._drive(now, err)

    def _stuck(self, now: float, pos: float) -> Step | None:
        """Too slow, or the home switch still closed well above home: FAULT."""
        if self.timer.expired(now):
            return self._fail(
                FaultCode.TILT_TIMEOUT,
                f"tilt did not reach {self.target:g}° within {self.timer.limit_s:.1f} s"
                f" (at {pos:.1f}°)",
            )
        if self.axis.is_home() and pos > self.cfg.tolerance_deg * 3:
            return self._fail(
                FaultCode.TILT_HOME_STUCK,
                f"tilt home switch still closed at {pos:.1f}° (stuck closed)",
            )
        return None

    def _settle(self, err: float) -> Step | None:
        """Stopped: DONE within tolerance, else the way to correct (None), or FAULT after
        too many corrections."""
        if abs(err) <= self.cfg.tolerance_deg:
            return self._below_zero_open() or Step.DONE
        self._corrections += 1
        if self._corrections > self.MAX_CORRECTIONS:
            return self._fail(
                FaultCode.TILT_TIMEOUT,
                f"tilt could not settle within ±{self.cfg.tolerance_deg:g}° of {self.target:g}°",
            )
        self._dir = TiltDirection.UP if err > 0 else TiltDirection.DOWN
        self._sup.reset()
        self._zero.reset()
        return None

    def _below_zero_open(self) -> Step | None:
        """The home switch witness at rest: below 0° by the calibration, the switch must be
        closed (it closes at 0° going down and opens at or above it going up)."""
        cal, raw = self.axis.calibration, self.axis.read_raw()
        if cal is None or self.axis.is_home():
            return None
        deg, tol = cal.degrees(raw), self.cfg.home_tolerance_deg
        if deg >= -tol:
            return None
        return self._fault(off_zero(deg, raw, cal, tol, "is still open"))

    def _drive(self, now: float, err: float) -> Step:
        assert self._dir is not None
        if self._dir is TiltDirection.DOWN:  # the home switch witness on the way down
            fault = self._zero.down(
                now, self.axis.read_raw(), self.axis.is_home(), self.axis.calibration
            )
            if fault is not None:
                return self._fault(fault)
        reached = abs(err) <= self.cfg.tolerance_deg / 2 or (
            err <= 0 if self._dir is TiltDirection.UP else err >= 0
        )
        if reached:
            self.axis.stop()
            self._dir = None
            return Step.BUSY
        fault = self._sup.drive(now, self._dir)
        return Step.BUSY if fault is None else self._fault(fault)

    def halt(self) -> None:
        super().halt()
        self._dir = None

    def resume(self, now: float) -> None:
        self.timer.stop()  # re-armed from the distance left at the next update
        self._corrections = 0
        self._sup.reset()
        self._zero.reset()


class RotateRevolutions(AxisController[RotateAxis, RotateSection]):
    """Turn N whole revolutions: each ends on the next closing edge of the home switch, and
    takes the calibrated time (`RevolutionCheck`). The last edge is where the axis stops: seen
    across scans too far apart to know where that is (a stall), the edge is approached again
    from the defined side (`RotateHome`), which ends at 0° whichever way the step turned."""

    axis_name = "rotate"

    def __init__(
        self,
        axis: RotateAxis,
        cfg: RotateSection,
        cal: RotateCalibration,
        direction: Direction,
        revolutions: int,
    ) -> None:
        super().__init__(axis, cfg)
        self.direction = direction
        self.cal = cal
        # The switch closes at 0° turning CW and at the end of its arc turning CCW.
        self.target_deg = 0.0 if direction is Direction.CW else cal.home_arc_deg
        self.total = revolutions
        self.done = 0
        self._left: bool | None = None
        self._last: float | None = None
        self.timer.limit_s = cfg.revolution_timeout_s
        self.check = RevolutionCheck(cfg, cal, direction)
        self.final: RotateHome | None = None
        """The final approach, when the last edge was seen across a stall."""
        self.stopped: OnSwitch | None = None
        """Stopped on the last edge, until a later scan reads the switch still closed."""

    def update(self, now: float) -> Step:
        if self.final is not None:
            return self._step(self.final, now)
        home = self.axis.is_home()
        if self.stopped is not None:
            return self._on_switch(now, home)
        if not self.timer.started:
            self.timer.start(now)
            self.check.start(now)
            self._left = not home
        before, self._last = self._last, now
        if not self._left:
            self._left = not home
        elif home:
            self.done += 1
            self._left = False
            self.timer.start(now)
            fault = self.check.edge(now)
            if fault is not None:
                return self._fault(fault)
            if self.done >= self.total:
                self.axis.stop()
                return self._last_edge(now, before)
        if self.timer.expired(now):
            return self._fail(
                FaultCode.ROTATE_HOME_TIMEOUT,
                f"rotate home switch not seen within {self.cfg.revolution_timeout_s:g} s during"
                f" revolution {self.done + 1} of {self.total}",
            )
        fault = self.check.overdue(now)
        if fault is not None:
            return self._fault(fault)
        self.axis.drive(self.direction)
        return Step.BUSY

    def _last_edge(self, now: float, before: float | None) -> Step:
        if half_travel(self.cal.speed_dps, before, now) <= self.cfg.latch_tolerance_deg:
            self.stopped = OnSwitch(now)
            return Step.BUSY
        self._approach_again()
        return Step.BUSY

    def _on_switch(self, now: float, home: bool) -> Step:
        """The session ends on the switch: a stop written late ran past it (`OnSwitch`)."""
        assert self.stopped is not None
        step = self.stopped.step(now, home)
        if step is not None:
            return step
        self._approach_again()
        return Step.BUSY

    def _approach_again(self) -> None:
        """The last edge, seen where the rotate may not stop on it: approach it again. Turning
        CW the rotate runs on past the switch's arc, which is then behind it, the way
        `RotateHome` backs off; turning CCW it runs on below 0°, short of where the seek
        finds the switch."""
        # The relay was just on: it rests before the back-off reverses the drive.
        self.final = RotateHome(self.axis, self.cfg, self.cal.speed_dps, REVERSE_DWELL_S)
        self.final.behind = self.direction is Direction.CW
        self.target_deg = 0.0

    def halt(self) -> None:
        if self.final is None and self._left and self.axis.is_home():
            self._edge_at_halt()
        super().halt()
        if self.final is not None:
            self.final.halt()

    def _edge_at_halt(self) -> None:
        """The scan that halts (a Pause, the E-stop, the deadman: each acts before `update`)
        read the switch closed after the rotate had left it: that is a revolution's edge, and
        counted now, for the rotate may run on past the arc before its outputs go off (a scan
        stalled before its write, a seat that coasts) and the resumed step would never see it:
        one revolution too many (CI, test_session: 4.0 turned for 3 counted). Where it stops
        is unknown, so a last edge is approached again on resume (`RotateHome`)."""
        self.done += 1
        self._left = False
        if self.done >= self.total:
            self._approach_again()

    def resume(self, now: float) -> None:
        super().resume(now)
        self.check.resume(now)
        self._last = None
        if self.final is not None:
            self.final.resume(now)


class SessionRun(Chain):
    """A session's steps as a chain, with progress for the status record."""

    def __init__(
        self, session: Session, devices: Devices, config: MachineConfig, cal: RotateCalibration
    ) -> None:
        tilt, rotate = devices.tilt, devices.rotate

        def make(step: TiltStep | RotateStep) -> Callable[[], Controller]:
            if isinstance(step, TiltStep):
                return lambda: TiltMove(tilt, config.tilt, step.degrees)
            return lambda: RotateRevolutions(
                rotate, config.rotate, cal, step.direction, step.revolutions
            )

        super().__init__([make(s) for s in session.steps])
        self.session = session

    def revolutions_done(self) -> int:
        steps = self.session.steps
        done = sum(s.revolutions for s in steps[: self.index] if isinstance(s, RotateStep))
        if isinstance(self.current, RotateRevolutions):
            done += self.current.done
        return done

    def progress(self) -> SessionProgress:
        steps = self.session.steps
        done = self.revolutions_done()
        total = sum(s.revolutions for s in steps if isinstance(s, RotateStep))
        step = steps[self.index] if self.index < len(steps) else None
        target = next(
            (s.degrees for s in reversed(steps[: self.index + 1]) if isinstance(s, TiltStep)),
            None,
        )
        return SessionProgress(
            name=self.session.name,
            step_index=self.index,
            step_count=len(steps),
            step_kind=step.kind if step is not None else None,
            revolutions_done=done,
            revolutions_total=total,
            tilt_target_deg=target,
        )
