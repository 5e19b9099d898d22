"""Machine states and the `Status` record published on `machine/<id>/status`."""

from __future__ import annotations

from enum import StrEnum

from pydantic import Field

from ride_machine.schema import SCHEMA_VERSION

from .base import OpenWireModel


class MachineState(StrEnum):
    """Every state of the machine; the string is what the wire carries."""

    IDLE = "IDLE"
    HOMING = "HOMING"
    CALIBRATING = "CALIBRATING"
    RUNNING = "RUNNING"
    PAUSED = "PAUSED"
    DONE = "DONE"
    FAULT_ESTOP = "FAULT_ESTOP"
    FAULT_HW = "FAULT_HW"
    WARNING_NEEDS_CALIBRATION = "WARNING_NEEDS_CALIBRATION"
    WARNING_NOT_HOME = "WARNING_NOT_HOME"


MOTION_STATES = frozenset({MachineState.HOMING, MachineState.CALIBRATING, MachineState.RUNNING})
"""States in which a controller may energise a relay."""

FAULT_STATES = frozenset({MachineState.FAULT_ESTOP, MachineState.FAULT_HW})


class FaultCode(StrEnum):
    """Why the machine is in a fault state."""

    ESTOP = "ESTOP"
    ROTATE_HOME_TIMEOUT = "ROTATE_HOME_TIMEOUT"
    TILT_HOME_TIMEOUT = "TILT_HOME_TIMEOUT"
    TILT_NOT_FOLLOWING = "TILT_NOT_FOLLOWING"
    TILT_TIMEOUT = "TILT_TIMEOUT"
    TILT_SIGNAL_NOISY = "TILT_SIGNAL_NOISY"
    TILT_SIGNAL_RANGE = "TILT_SIGNAL_RANGE"
    TILT_HOME_STUCK = "TILT_HOME_STUCK"
    CALIBRATION_IMPLAUSIBLE = "CALIBRATION_IMPLAUSIBLE"
    CALIBRATION_NOT_REPEATABLE = "CALIBRATION_NOT_REPEATABLE"
    """A calibration measured its reference twice and the two disagree (both in the message)."""
    HOME_EDGE_UNCERTAIN = "HOME_EDGE_UNCERTAIN"
    """The home switch edge was seen only across scans too far apart, in every approach."""
    HOME_OFF_ZERO = "HOME_OFF_ZERO"
    """The home switch witness: the tilt's switch closed outside the tolerance of the
    calibrated zero (at Home, a calibration's verification, or a pass on the way down)."""
    TILT_SPEED_IMPLAUSIBLE = "TILT_SPEED_IMPLAUSIBLE"
    """The tilt's measured speed disagrees with its nominal speed: wrong gain or bad sensor."""
    TILT_GAIN_MISMATCH = "TILT_GAIN_MISMATCH"
    """The drive's speed witness (counts per second over a stroke) disagrees with the
    calibrated gain: a wrong, stale or slipped calibration, or a drive off its nominal speed."""
    ROTATE_SPEED_IMPLAUSIBLE = "ROTATE_SPEED_IMPLAUSIBLE"
    """A revolution took far less than the calibrated time: wrong calibration or a bad switch."""
    INVALID_SESSION = "INVALID_SESSION"
    WATCHDOG = "WATCHDOG"
    DAEMON_DIED = "DAEMON_DIED"
    LOOP_EXCEPTION = "LOOP_EXCEPTION"
    DUPLICATE_ID = "DUPLICATE_ID"
    """Another session holds this machine's id (two daemons, one id): motion stopped."""


class Fault(OpenWireModel):
    """The active fault: a code for scripts and a message for people."""

    code: FaultCode
    message: str
    axis: str | None = None


class SessionProgress(OpenWireModel):
    """Where the running session is."""

    name: str
    step_index: int
    step_count: int
    step_kind: str | None = None
    revolutions_done: int = 0
    revolutions_total: int = 0
    tilt_target_deg: float | None = None


class AxesFlags(OpenWireModel):
    """A yes/no per axis (calibrated, homed)."""

    tilt: bool = False
    rotate: bool = False


class EstopInfo(OpenWireModel):
    """E-stop input and latch: `latched` stays true after release until Resume/Home/Stop."""

    active: bool = False
    latched: bool = False


class MotionRef(OpenWireModel):
    """The motion command in progress (running, paused or halted by an E-stop): the
    transaction whose completion notice (`machine/<id>/done/<transaction_id>`) is still due."""

    transaction_id: str
    command: str
    started_at: float


class Status(OpenWireModel):
    """The machine's status, published on every change and as a heartbeat."""

    schema_version: int = SCHEMA_VERSION
    machine_id: str
    state: MachineState
    previous_state: MachineState | None = None
    session: SessionProgress | None = None
    warnings: list[str] = Field(default_factory=list)
    fault: Fault | None = None
    estop: EstopInfo = EstopInfo()
    calibrated: AxesFlags = AxesFlags()
    homed: AxesFlags = AxesFlags()
    tilt_deg: float | None = None
    rotate_deg: float | None = None
    rider_connected: bool = False
    motion: MotionRef | None = None
    seq: int
    cycle: int
    time: float
    uptime_s: float = 0.0
    heartbeat_s: float | None = None
    """The machine republishes its status at least this often (`bus.heartbeat_s`): a reader
    may call it lost after a longer silence. None from a machine older than this field."""
