"""The simulator HAL (the default backend): the ride's physics behind a process image."""

from __future__ import annotations

import random
from collections.abc import Callable

from ride_machine.hal.base import Inputs, Outputs
from ride_machine.hal.iomap import RELAY_OUTPUTS, IoMap, Signal

from .physics import ChargePumpRelay, SwitchFault, World, WorldInputs
from .settings import PhysicsParams


class SimHal:
    """A `Hal` whose world advances on the loop's clock, so tests step it without sleeping.

    Fault injection is a plain API (`press_estop`, `stick_home`, `freeze_tilt_ai`, ...).
    `sleep` is how a scan stall passes (`stall_scans`): `time.sleep` in the daemon, the fake
    clock's `advance` in a test; None (a world stepped by someone else) never stalls.
    """

    def __init__(
        self,
        clock: Callable[[], float],
        iomap: IoMap | None = None,
        params: PhysicsParams | None = None,
        sleep: Callable[[float], object] | None = None,
    ) -> None:
        self._clock = clock
        self.iomap = iomap or IoMap()
        self.world = World(params=params or PhysicsParams())
        p = self.world.params
        if self.iomap.charge_pump is not None:  # the ride's drives hang on the pump's relay
            self.world.pump = ChargePumpRelay(p.charge_pump_timeout_s)
        self._sleep = sleep
        self._stalls = random.Random(p.seed + 1)
        self.stall_probability = p.scan_stall_probability
        self.stall_max_s = p.scan_stall_max_s
        self.stalled_s = 0.0
        """Time the injected scan stalls took so far."""
        self._last = clock()
        self._relays = self.iomap.channels(RELAY_OUTPUTS)
        self._written = Outputs(ro=dict.fromkeys(self._relays, False))
        self._sensed: WorldInputs | None = None
        self._still: tuple[object, ...] | None = None
        """`World.still()` at the latest sense; the same again means the same image."""
        self.still_scans = True
        """Reuse the image while the world is still (`World.still`); False senses every scan
        (the tests compare the two)."""
        self.reused = 0
        """Scans that found the world still and reused the image without sensing."""
        self._inputs = Inputs(di={}, ai={})
        self.scans = 0
        self.writes = 0
        self.closed = False
        self._apply(self._written)

    # -- Hal protocol -------------------------------------------------------------------
    def scan_inputs(self) -> Inputs:
        self._advance()
        self.scans += 1
        world = self.world
        still = world.still() if self.still_scans else None
        if still is not None and still == self._still:
            self.reused += 1
            return self._inputs  # no relay on, no noise, nothing it reads changed
        self._still = still
        sensed = world.sense()
        if sensed == self._sensed:
            return self._inputs  # an image is never changed in place: the same one again
        self._sensed = sensed
        m = self.iomap
        estop_level = (not sensed.estop_pressed) if m.estop_active_low else sensed.estop_pressed
        self._inputs = Inputs(
            di={
                m.rotate_home: sensed.rotate_home,
                m.tilt_home: sensed.tilt_home,
                m.estop: estop_level,
            },
            ai={m.tilt_position: sensed.tilt_raw},
        )
        return self._inputs

    def scan_outputs(self, outputs: Outputs) -> None:
        self.writes += 1
        if self.stall_probability and self._sleep is not None:
            self._stall(self._sleep)  # decided, not yet written: the old outputs run on
        pump = self.world.pump
        if pump is not None and outputs.pump is not None and outputs.pump != pump.level:
            self._advance()  # the drives had power up to now as the relay had it
            pump.feed(outputs.pump, self.world.time)
        if outputs.ro == self._written.ro:
            return  # the drive runs on these already: the next scan integrates up to then
        self._advance()
        self._written = Outputs(ro={ch: bool(outputs.ro.get(ch, False)) for ch in self._relays})
        self._apply(self._written)

    def force_all_outputs_safe(self) -> None:
        self._advance()
        self._written = Outputs(ro=dict.fromkeys(self._relays, False))
        self._apply(self._written)
        if self.world.pump is not None:
            self.world.pump.feed(False, self.world.time)  # the pump stops: low, for good

    def read_estop(self) -> bool:
        return self.world.faults.estop_pressed

    def close(self) -> None:
        self.force_all_outputs_safe()
        self.closed = True

    # -- observation --------------------------------------------------------------------
    def now(self) -> float:
        """The clock the world runs on, now."""
        return self._clock()

    @property
    def outputs(self) -> Outputs:
        """What was last written to the relays."""
        return Outputs(ro=dict(self._written.ro))

    def relay(self, signal: Signal) -> bool:
        return self._written.ro[self.iomap.channel(signal)]

    # -- fault injection ----------------------------------------------------------------
    def press_estop(self) -> None:
        self.world.faults.estop_pressed = True

    def release_estop(self) -> None:
        self.world.faults.estop_pressed = False

    def stick_home(self, axis: str, fault: SwitchFault | None) -> None:
        """Stick the `rotate` or `tilt` home switch open or closed (None clears it)."""
        setattr(self.world.faults, f"{_axis(axis)}_home", fault)

    def freeze_tilt_ai(self, frozen: bool = True) -> None:
        self.world.faults.tilt_ai_frozen = frozen

    def break_tilt_wire(self, reads: int | None) -> None:
        """The tilt sensor's wiring broken: the input reads `reads` (0 an open circuit, 32767
        a short to the supply) whatever the seat does; None repairs it."""
        self.world.faults.tilt_ai_broken = reads

    def set_tilt_noise(self, counts: float) -> None:
        if counts < 0:
            raise ValueError("noise amplitude must be >= 0 counts")
        self.world.faults.tilt_ai_noise_counts = counts

    def stall(self, axis: str, stalled: bool = True) -> None:
        """A drive that gets power but does not move (a seized gearbox, a blown fuse)."""
        setattr(self.world.faults, f"{_axis(axis)}_stalled", stalled)

    def clear_faults(self) -> None:
        """Every injected fault repaired; the configured noise (`[hal.sim]`) stays."""
        f = self.world.faults
        f.rotate_home = f.tilt_home = None
        f.tilt_ai_frozen = False
        f.tilt_ai_broken = None
        f.tilt_ai_noise_counts = self.world.params.tilt_noise_counts
        f.rotate_stalled = f.tilt_stalled = False

    def stall_scans(self, probability: float, max_s: float) -> None:
        """From now on each scan stalls with `probability`, for up to `max_s` (uniform), before
        writing its outputs (the old ones run on meanwhile): the outputs and the next cycle
        come that much late, as when a host preempts the scan thread mid-cycle."""
        if not (0.0 <= probability <= 1.0 and 0.0 <= max_s <= 1.0):
            raise ValueError("stall probability must be in 0..1 and max_s in 0..1 s")
        self.stall_probability, self.stall_max_s = probability, max_s

    def place(self, tilt_deg: float | None = None, rotate_deg: float | None = None) -> None:
        """Put the axes somewhere else (`World.place`), integrating up to now first."""
        self._advance()
        self.world.place(tilt_deg, rotate_deg)

    # -- internals ----------------------------------------------------------------------
    def _stall(self, sleep: Callable[[float], object]) -> None:
        if self._stalls.random() < self.stall_probability:
            stall = self._stalls.uniform(0.0, self.stall_max_s)
            self.stalled_s += stall
            sleep(stall)

    def _advance(self) -> None:
        """Integrate up to now under the old outputs before they change."""
        now = self._clock()
        dt = now - self._last
        self._last = now
        world = self.world
        drive = world.drive
        if drive.rotate_on or drive.tilt_on:
            world.step(dt)
        elif dt > 0:
            world.time += dt  # `step` with no relay on moves nothing (an idle cycle's call)

    def _apply(self, outputs: Outputs) -> None:
        m, d = self.iomap, self.world.drive
        d.rotate_on = outputs.ro[m.rotate_relay]
        d.rotate_ccw = outputs.ro[m.rotate_dir]
        d.tilt_on = outputs.ro[m.tilt_relay]
        d.tilt_up = outputs.ro[m.tilt_dir]


def _axis(axis: str) -> str:
    if axis not in ("rotate", "tilt"):
        raise ValueError(f"unknown axis {axis!r}; expected 'rotate' or 'tilt'")
    return axis
