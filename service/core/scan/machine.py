"""The assembled core: HAL → process image → devices → state machine → scan loop."""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable

from ride_machine.hal.base import Hal
from ride_machine.service.config.axes import TiltSection
from ride_machine.service.config.model import LiveConfig, MachineConfig
from ride_machine.service.core.history.events import EventRecorder, EventSink, NullEventSink
from ride_machine.service.core.motion.devices import Calibration, Devices
from ride_machine.service.core.motion.io import IoPoints, ProcessImage
from ride_machine.service.core.motion.scale import scale_problem
from ride_machine.service.core.statemachine import StateMachine, Transition
from ride_machine.service.core.statemachine.deadman import Heartbeats
from ride_machine.service.core.storage.persist import CalibrationStore

from .loop import ScanLoop
from .sink import LoopSink
from .watchdog import GuardedHal

log = logging.getLogger("machine")


def log_transition(t: Transition) -> None:
    log.info("event=state old=%s new=%s reason=%r", t.old, t.new, t.reason)


class Machine:
    """Everything below the bus, wired together; outputs are made safe before anything else."""

    def __init__(  # noqa: PLR0913 - keyword-only wiring of the assembled core
        self,
        config: MachineConfig | LiveConfig,
        hal: Hal,
        *,
        now: float,
        wall_offset: float = 0.0,
        store: CalibrationStore | None = None,
        sink: LoopSink | None = None,
        beats: Heartbeats | None = None,
        on_transition: Callable[[Transition], None] | None = log_transition,
        events: EventSink | None = None,
        guard: GuardedHal | None = None,
        warnings: list[str] | None = None,
        clock: Callable[[], float] | None = None,
    ) -> None:
        """`config`: fixed, or live (online parameters); `sink` gets what the loop publishes;
        `beats` records the Riders' heartbeats (the bus feeds it through the loop's port);
        `events` receives the event history (`service/core/history/events.py`) and must never block;
        `warnings` start in the status; `clock`: the real clock the runner reads `now` from
        (`ScanLoop.clock`)."""
        hal.force_all_outputs_safe()
        self.live = config if isinstance(config, LiveConfig) else LiveConfig(config)
        self.hal = hal
        self.store = store
        self.image = ProcessImage(self.live.current.hal.iomap)
        self.points = IoPoints(self.image)
        self.devices = Devices(self.points)
        calibration, found = _stored_calibration(store, self.live.current.tilt)
        self.recorder = EventRecorder(
            events or NullEventSink(),
            period_s=self.live.current.loop.period_s,
            wall_offset=wall_offset,
            persisted=store is not None,
        )
        self.state_machine = StateMachine(
            devices=self.devices,
            live=self.live,
            calibration=calibration,
            on_calibrated=store.save if store is not None else None,
            storage=store.health if isinstance(store, CalibrationStore) else None,
            on_transition=_both(on_transition, self.recorder.transition),
            wall_offset=wall_offset,
            warnings=[*found, *(warnings or [])],
        )
        self.loop = ScanLoop(
            hal,
            self.state_machine,
            self.recorder,
            sink=sink,
            started_at=now,
            guard=guard,
            beats=beats,
            clock=clock,
        )


def _stored_calibration(
    store: CalibrationStore | None, tilt: TiltSection
) -> tuple[Calibration, list[str]]:
    """The calibration the machine powers up with, and the warnings its load gives: a file that
    could not be read, or a tilt calibration outside the sensor's commissioned scale (a file
    from another machine, edited, or from before the scale was commissioned), which is not
    used: the tilt needs calibrating again, and the file stays as it is."""
    if store is None:
        return Calibration(), []
    calibration, warning = store.load()
    warnings = [warning] if warning else []
    cal = calibration.tilt
    outside = (
        None if cal is None else scale_problem(cal.offset_counts, cal.gain_counts_per_deg, tilt)
    )
    if outside is not None:
        calibration = dataclasses.replace(calibration, tilt=None)
        warnings.append(f"stored {outside.message}; not used: calibrate the tilt again")
    for found in warnings:
        log.warning("event=calibration_load_failed detail=%r", found)
    return calibration, warnings


def _both(
    first: Callable[[Transition], None] | None, second: Callable[[Transition], None]
) -> Callable[[Transition], None]:
    if first is None:
        return second

    def both(t: Transition) -> None:
        first(t)
        second(t)

    return both
