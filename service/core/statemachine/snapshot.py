"""`Snapshot`: the state machine at one moment, as one frozen value compared with `==`.

It holds everything the status shows of the machine and everything else the next cycle acts
on; the scan loop builds the status from it, publishes when it differs from the last one, and
lets a cycle be quiet while nothing could make it differ (service/core/scan/loop.py). A field the
status needs is read from here, so it cannot be left out of the comparison.
"""

from __future__ import annotations

from dataclasses import dataclass

from ride_machine.schema.status import AxesFlags, EstopInfo, Fault, MachineState, Status
from ride_machine.service.core.motion.controllers import SessionRun
from ride_machine.service.core.motion.devices import Calibration

from .context import Motion


@dataclass(frozen=True, slots=True)
class Snapshot:
    """What the status shows (first) and what else a cycle acts on (last)."""

    state: MachineState
    previous_state: MachineState | None
    fault: Fault | None
    estop_active: bool
    """The E-stop input as scanned."""
    estop_latched: bool
    calibration: Calibration
    home_tilt: bool
    """Referenced and on its home switch now."""
    home_rotate: bool
    session: SessionRun | None
    """The session under way or last run (the status shows its progress)."""
    step: int | None
    revolutions: int | None
    motion: Motion | None
    """The motion whose completion notice is still due."""
    rider_connected: bool
    warnings: tuple[str, ...]
    rider_warning: str | None
    storage: int
    """The data dir's health version: its warnings are part of the status."""
    rider: str | None
    """The controlling Rider, whose heartbeats the deadman judges."""
    resume_to: MachineState | None
    estop_from: MachineState | None
    duplicate_of: tuple[str, ...]


def status_of(  # noqa: PLR0913 - the status's own fields besides the machine's
    shown: Snapshot,
    *,
    machine_id: str,
    storage_warnings: list[str],
    tilt_deg: float | None,
    rotate_deg: float | None,
    seq: int,
    cycle: int,
    time: float,
    uptime_s: float,
    heartbeat_s: float,
) -> Status:
    """The status of the machine as `shown`, with what else it reports (the data dir's
    warnings, positions, times): every field of the machine's own comes from `shown`, so none
    can change without the comparison of two snapshots noticing."""
    cal, run, motion = shown.calibration, shown.session, shown.motion
    warnings = list(shown.warnings)
    if shown.rider_warning:
        warnings.append(shown.rider_warning)
    return Status(
        machine_id=machine_id,
        state=shown.state,
        previous_state=shown.previous_state,
        session=run.progress() if run is not None else None,
        warnings=warnings + storage_warnings,
        fault=shown.fault,
        estop=EstopInfo(active=shown.estop_active, latched=shown.estop_latched),
        calibrated={"tilt": cal.tilt is not None, "rotate": cal.rotate is not None},
        homed=AxesFlags(tilt=shown.home_tilt, rotate=shown.home_rotate),
        tilt_deg=tilt_deg,
        rotate_deg=rotate_deg,
        rider_connected=shown.rider_connected,
        motion=motion.ref() if motion is not None else None,
        seq=seq,
        cycle=cycle,
        time=time,
        uptime_s=uptime_s,
        heartbeat_s=heartbeat_s,
    )
