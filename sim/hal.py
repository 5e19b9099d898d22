"""The simulator HAL (the default backend): the ride's physics behind a process image."""

from __future__ import annotations

from collections.abc import Callable

from hal.base import Inputs, Outputs
from hal.iomap import RELAY_OUTPUTS, IoMap, Signal
from service.config.model import PhysicsParams
from sim.physics import SwitchFault, World, WorldInputs


class SimHal:
    """A `Hal` whose world advances on the loop's clock, so tests step it without sleeping.

    Fault injection is a plain API (`press_estop`, `stick_home`, `freeze_tilt_ai`, ...).
    """

    def __init__(
        self,
        clock: Callable[[], float],
        iomap: IoMap | None = None,
        params: PhysicsParams | None = None,
    ) -> None:
        self._clock = clock
        self.iomap = iomap or IoMap()
        self.world = World(params=params or PhysicsParams())
        p = self.world.params
        self.max_step_s = 0.5 * p.home_arc_deg / p.rotate_speed_dps
        """The most the world advances between two looks at it: half the time the rotate axis
        takes to cross its home switch. A scan thread that the host stalls for longer (a shared
        CI machine: 30-100 ms now and then) pauses the simulated ride with it instead of letting
        it turn past the switch unseen, which made a session turn 7 revolutions for 6 (a real
        machine's watchdog trips long before; tests relax it for loaded hosts)."""
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
        if outputs.ro == self._written.ro:
            return  # the drive runs on these already: the next scan integrates up to then
        self._advance()
        self._written = Outputs(ro={ch: bool(outputs.ro.get(ch, False)) for ch in self._relays})
        self._apply(self._written)

    def force_all_outputs_safe(self) -> None:
        self._advance()
        self._written = Outputs(ro=dict.fromkeys(self._relays, False))
        self._apply(self._written)

    def read_estop(self) -> bool:
        return self.world.faults.estop_pressed

    def close(self) -> None:
        self.force_all_outputs_safe()
        self.closed = True

    # -- observation --------------------------------------------------------------------
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

    def set_tilt_noise(self, counts: float) -> None:
        if counts < 0:
            raise ValueError("noise amplitude must be >= 0 counts")
        self.world.faults.tilt_ai_noise_counts = counts

    def stall(self, axis: str, stalled: bool = True) -> None:
        """A drive that gets power but does not move (a seized gearbox, a blown fuse)."""
        setattr(self.world.faults, f"{_axis(axis)}_stalled", stalled)

    def clear_faults(self) -> None:
        f = self.world.faults
        f.rotate_home = f.tilt_home = None
        f.tilt_ai_frozen = False
        f.tilt_ai_noise_counts = 0.0
        f.rotate_stalled = f.tilt_stalled = False

    # -- internals ----------------------------------------------------------------------
    def _advance(self) -> None:
        """Integrate up to now under the old outputs before they change."""
        now = self._clock()
        dt = now - self._last
        self._last = now
        world = self.world
        dt = dt if dt < self.max_step_s else self.max_step_s
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
