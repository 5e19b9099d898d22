"""The physical world behind a RevPi process image: relays in, sensors out, for tests.

It plays the field wiring against the same image file the `RevPiHal` uses, with revpimodio2 in
simulator mode (inputs and outputs swapped), and the simulator HAL's physics, faults and IO
mapping, so the RevPi backend runs the same sessions as the simulator end to end.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from ride_machine.hal.base import HalError, Outputs
from ride_machine.hal.iomap import ANALOG_INPUTS, DIGITAL_INPUTS, RELAY_OUTPUTS, IoMap, Signal
from ride_machine.hal.pictory import read_config
from ride_machine.hal.revpi import bind_ios, open_modio, raise_for_errors

from .hal import SimHal
from .physics import World
from .settings import PhysicsParams


class ProcImgSim:
    """Each `step()`: the relays the loop wrote → physics up to now → sensors into the image.

    The world's drive changes when the loop wrote the relays (the previous step's time), then
    the world moves to now, as with `SimHal`. Call `step()` after advancing the shared clock and
    before `ScanLoop.step()`. Inject faults on `ride` (a `SimHal`: `ride.press_estop()`, ...).
    """

    def __init__(
        self,
        iomap: IoMap,
        procimg: str,
        configrsc: str,
        clock: Callable[[], float],
        params: PhysicsParams | None = None,
    ) -> None:
        read_config(configrsc)
        self._clock = clock
        self._t = clock()
        self.ride = SimHal(lambda: self._t, iomap, params)
        self._rpi, _ = open_modio(configrsc, procimg, simulator=True)
        try:
            bound, findings = bind_ios(self._rpi, iomap)
            raise_for_errors(findings)
        except BaseException:
            self._rpi.cleanup()
            raise
        ios = {b.signal: b for b in bound}
        self._di = [ios[s] for s in DIGITAL_INPUTS]
        self._ai = [ios[s] for s in ANALOG_INPUTS]
        self._ro = [ios[s] for s in RELAY_OUTPUTS]
        self._pump = ios.get(Signal.CHARGE_PUMP)
        # Only the modules carrying our sensors are written, so the HAL's bytes stay the HAL's.
        sensors = [b.io for b in self._di + self._ai]
        self._sensor_devices = [d for d in self._rpi.device if any(io in d for io in sensors)]
        self.steps = 0
        self.closed = False
        self.step()

    @property
    def world(self) -> World:
        """The ride's mechanics (positions, drive, faults)."""
        return self.ride.world

    def step(self) -> None:
        """Read the relays, advance the physics to the clock's now, write the sensors."""
        if self.closed:
            raise HalError("procimg sim: closed")
        rpi = self._rpi
        if not rpi.readprocimg():
            raise HalError("procimg sim: cannot read the process image")
        pump = None if self._pump is None else self._pump.read_bool()
        self.ride.scan_outputs(Outputs({b.channel: b.read_bool() for b in self._ro}, pump))
        self._t = self._clock()
        sensed = self.ride.scan_inputs()
        for b in self._di:
            b.write_bool(sensed.di[b.channel])
        for b in self._ai:
            b.io.value = sensed.ai[b.channel]
        for dev in self._sensor_devices:
            if not rpi.writeprocimg(dev):
                raise HalError("procimg sim: cannot write the process image")
        self.steps += 1

    @property
    def time(self) -> float:
        """The clock at the last `step()`: the time the world has been advanced to."""
        return self._t

    def relays(self) -> dict[str, bool]:
        """The relay outputs as the field sees them after the last `step()`."""
        return self.ride.outputs.ro

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            self._rpi.cleanup()

    def __enter__(self) -> ProcImgSim:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
