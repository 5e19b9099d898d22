"""What every controller is made of: the `Step` a cycle ends in, the timeout window, the base
classes, and the chain that runs controllers one after another.

Controllers are non-blocking: each `update(now)` looks at the inputs and sets the outputs once.
They read no clock (time comes in as `now`), touch no IO beyond the devices, and never block.
A controller ends `DONE` or `FAULT` (with a `Fault` saying why); `halt()` drops its outputs for a
pause or an E-stop and `resume(now)` restarts its timeout windows, so paused time never counts.
Every window is a `Timeout`; phases are enums; single-axis controllers share `AxisController`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from enum import Enum, auto
from typing import Generic, TypeVar

from ride_machine.schema.status import Fault, FaultCode
from ride_machine.service.config.axes import RotateSection, TiltSection

from .devices import RotateAxis, TiltAxis


class Step(Enum):
    """What one `update` of a controller came to (a motion's own ending is a completion
    notice's `schema.completion.Outcome`)."""

    BUSY = auto()
    DONE = auto()
    FAULT = auto()


REVERSE_DWELL_S = 0.2
"""Relay off this long before a motor reverses, so a contactor never swaps direction under load."""


class Timeout:
    """A window timer in the manner of revpimodio2's Cycletools timers, on the time that comes
    in: `start(now, limit_s)`, then `elapsed(now)`; `expired(now)` once past the limit (a
    timeout), `done(now)` once the limit is reached (a dwell or a timed stroke is over).
    `resume(now)` starts the window again after a pause or an E-stop: paused time never counts."""

    __slots__ = ("_t0", "limit_s")

    def __init__(self, limit_s: float = 0.0) -> None:
        self.limit_s = limit_s
        self._t0: float | None = None

    @property
    def started(self) -> bool:
        return self._t0 is not None

    def start(self, now: float, limit_s: float | None = None) -> None:
        self._t0 = now
        if limit_s is not None:
            self.limit_s = limit_s

    def resume(self, now: float) -> None:
        self._t0 = now

    def stop(self) -> None:
        """Not running: the next `start` arms it afresh."""
        self._t0 = None

    def elapsed(self, now: float) -> float:
        assert self._t0 is not None, "a timer is read only once started"
        return now - self._t0

    def expired(self, now: float) -> bool:
        return self.elapsed(now) > self.limit_s

    def done(self, now: float) -> bool:
        return self.elapsed(now) >= self.limit_s


class Controller:
    """Base: a fault ends the controller with outputs stopped."""

    axis_name = ""
    target_deg: float | None = None
    """Where this controller leaves its axis (the settle check's target); None: nowhere fixed."""

    def __init__(self) -> None:
        self.fault: Fault | None = None

    def update(self, now: float) -> Step:
        raise NotImplementedError

    def halt(self) -> None:
        raise NotImplementedError

    def resume(self, now: float) -> None:
        raise NotImplementedError

    def abandon(self) -> None:
        """Stopped for good (Stop, Home over it): outputs off, nothing half-done kept."""
        self.halt()

    def active(self) -> Controller | None:
        """The controller doing the work now."""
        return self

    def _fault(self, fault: Fault) -> Step:
        self.halt()
        self.fault = fault
        return Step.FAULT

    def _fail(self, code: FaultCode, message: str) -> Step:
        return self._fault(Fault(code=code, message=message, axis=self.axis_name or None))

    def _step(self, sub: Controller, now: float) -> Step:
        """Run a sub-controller for one cycle; its fault is this controller's."""
        step = sub.update(now)
        if step is Step.FAULT:
            self.fault = sub.fault
        return step


AxisT = TypeVar("AxisT", RotateAxis, TiltAxis)
CfgT = TypeVar("CfgT", RotateSection, TiltSection)


class AxisController(Controller, Generic[AxisT, CfgT]):
    """One axis and its config section, with one `Timeout`: `halt()` stops the axis and
    `resume(now)` starts the window under way again."""

    def __init__(self, axis: AxisT, cfg: CfgT) -> None:
        super().__init__()
        self.axis: AxisT = axis
        self.cfg: CfgT = cfg
        self.timer = Timeout()

    def halt(self) -> None:
        self.axis.stop()

    def resume(self, now: float) -> None:
        self.timer.resume(now)


class Measurement(AxisController[AxisT, CfgT]):
    """A calibration: homing steps around a measurement. A paused homing step goes on; a
    paused measurement is worthless, so it re-homes and measures again."""

    homing: Controller | None
    """The homing step under way; None while measuring."""

    def resume(self, now: float) -> None:
        if self.homing is not None:
            self.homing.resume(now)
        else:
            self._start_over()

    def _start_over(self) -> None:
        raise NotImplementedError


class Chain(Controller):
    """Run controllers one after another; the next is built only when the previous is done."""

    def __init__(self, steps: Sequence[Callable[[], Controller]]) -> None:
        super().__init__()
        self._factories = list(steps)
        self.index = 0
        self.current: Controller | None = None

    def update(self, now: float) -> Step:
        while self.index < len(self._factories):
            if self.current is None:
                self.current = self._factories[self.index]()
            step = self._step(self.current, now)
            if step is not Step.DONE:
                return step
            self.current = None
            self.index += 1
        return Step.DONE

    def halt(self) -> None:
        if self.current is not None:
            self.current.halt()

    def abandon(self) -> None:
        if self.current is not None:
            self.current.abandon()

    def resume(self, now: float) -> None:
        if self.current is not None:
            self.current.resume(now)

    def active(self) -> Controller | None:
        """The controller doing the work now (through nested chains), if any."""
        return self.current.active() if self.current is not None else None
