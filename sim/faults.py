"""Simulator fault requests (`machine/<id>/sim/<fault>`): decode, apply, and report the world.

Shared by the daemon's bus (simulator HAL in-process) and the supervisor (the world runs there
while the daemon drives it through a process image), so both answer the same keys the same way.
"""

from __future__ import annotations

from pydantic import BaseModel

from ride_machine.schema.codec import DecodeError, decode_raw, sniff_format, validate
from ride_machine.schema.errors import Error, ErrorCode
from ride_machine.schema.sim import (
    SIM_REQUESTS,
    SimClear,
    SimEstop,
    SimHomeSwitch,
    SimPlace,
    SimStall,
    SimStalls,
    SimTiltSignal,
    SimWorldState,
    SwitchState,
)

from .hal import SimHal
from .physics import SwitchFault

WORLD = "world"
"""`sim/world`: read the world, change nothing."""


def decode_request(what: str, data: bytes, encoding: str | None) -> BaseModel:
    """The fault request for `sim/<what>`; `DecodeError` (its wire `Error`) for an unknown key
    (UNKNOWN_COMMAND) or a bad payload."""
    model = SIM_REQUESTS.get(what)
    if model is None:
        known = ", ".join([*SIM_REQUESTS, WORLD])
        message = f"unknown sim key {what!r}; known: {known}"
        raise DecodeError(Error(code=ErrorCode.UNKNOWN_COMMAND, message=message))
    body = data or b"{}"  # every field of a fault request has a default but the few required
    return validate(model, decode_raw(body, sniff_format(body, encoding)))


class HalSim:
    """The simulator HAL's fault injection (`hal.backends.Simulator`; the bus applies it on the
    scan thread, which owns the HAL)."""

    def __init__(self, sim: SimHal) -> None:
        self.sim = sim

    def decode(self, what: str, payload: bytes, encoding: str | None) -> BaseModel:
        return decode_request(what, payload, encoding)

    def apply(self, request: BaseModel) -> None:
        apply_fault(self.sim, request)

    def world(self, stamp: float) -> SimWorldState:
        return world_state(self.sim, stamp)


def apply_fault(sim: SimHal, req: BaseModel) -> None:
    """Inject (or repair) the fault a decoded request asks for."""
    if isinstance(req, SimEstop):
        if req.pressed:
            sim.press_estop()
        else:
            sim.release_estop()
    elif isinstance(req, SimHomeSwitch):
        fault = None
        if req.stuck is SwitchState.OPEN:
            fault = SwitchFault.STUCK_OPEN
        elif req.stuck is SwitchState.CLOSED:
            fault = SwitchFault.STUCK_CLOSED
        sim.stick_home(req.axis.value, fault)
    elif isinstance(req, SimTiltSignal):
        sim.freeze_tilt_ai(req.frozen)
        sim.set_tilt_noise(req.noise_counts)
    elif isinstance(req, SimStall):
        sim.stall(req.axis.value, req.stalled)
    elif isinstance(req, SimStalls):
        sim.stall_scans(req.probability, req.max_s)
    elif isinstance(req, SimPlace):
        sim.place(req.tilt_deg, req.rotate_deg)
    elif isinstance(req, SimClear):
        sim.clear_faults()


def world_state(sim: SimHal, stamp: float) -> SimWorldState:
    """The simulated world as the `sim/world` reply reports it."""
    w = sim.world
    f, p = w.faults, w.params
    return SimWorldState(
        time=stamp,
        tilt_deg=w.tilt_deg,
        rotate_deg=w.rotate_deg,
        revolutions=w.revolutions,
        estop_pressed=f.estop_pressed,
        relays=sim.outputs.ro,
        faults={
            "rotate_home": f.rotate_home,
            "tilt_home": f.tilt_home,
            "tilt_ai_frozen": f.tilt_ai_frozen,
            "tilt_ai_noise_counts": f.tilt_ai_noise_counts,
            "tilt_ai_broken": f.tilt_ai_broken,
            "rotate_stalled": f.rotate_stalled,
            "tilt_stalled": f.tilt_stalled,
            "scan_stall_probability": sim.stall_probability,
            "scan_stall_max_s": sim.stall_max_s,
        },
        tilt_home_closed=w.tilt_switch.closed,
        rotate_home_closed=w.rotate_switch.closed,
        tilt_zero_counts=p.ai_offset_counts + p.ai_gain_counts_per_deg * p.tilt_home_deg,
        stalled_s=sim.stalled_s,
        drives_powered=None if w.pump is None else w.pump.powered(w.time),
        drives_off_s=None if w.pump is None else max(0.0, w.time - w.pump.until),
        charge_pump_drops=None if w.pump is None else w.pump.drops,
        clock=sim.now(),
    )
