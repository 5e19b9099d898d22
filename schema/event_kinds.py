"""The kinds of event the machine records, apart from their models: `rider --help` lists them
without loading pydantic (schema/events.py serves it with the models)."""

from __future__ import annotations

from enum import StrEnum


class EventKind(StrEnum):
    """Every kind of event the machine records; the string is what the wire and the db carry."""

    COMMAND = "command"
    COMPLETION = "completion"
    STATE = "state"
    FAULT_RAISED = "fault_raised"
    FAULT_CLEARED = "fault_cleared"
    ESTOP_PRESSED = "estop_pressed"
    ESTOP_RELEASED = "estop_released"
    ESTOP_LATCHED = "estop_latched"
    ESTOP_RESET = "estop_reset"
    SESSION_STARTED = "session_started"
    SESSION_ENDED = "session_ended"
    CALIBRATION = "calibration"
    PARAM_CHANGED = "param_changed"
    SAFETY_CHANGED = "safety_changed"
    RIDER_LOST = "rider_lost"
    RIDER_RETURNED = "rider_returned"
    WATCHDOG_TRIP = "watchdog_trip"
    CLOCK_SET = "clock_set"
    DAEMON_START = "daemon_start"
    DAEMON_STOP = "daemon_stop"
    STORAGE_FAILED = "storage_failed"
    EVENTS_DROPPED = "events_dropped"
