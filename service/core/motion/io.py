"""Typed IO (`DI`, `AI`, `RO`) over the process image, named by the IO map."""

from __future__ import annotations

from dataclasses import dataclass

from ride_machine.hal.base import Inputs, Outputs
from ride_machine.hal.iomap import ANALOG_INPUTS, DIGITAL_INPUTS, RELAY_OUTPUTS, IoMap, Signal
from ride_machine.schema.io import IoKind, IoValue


class ProcessImage:
    """The cycle's copy of all IO: inputs as last scanned, outputs as they will be written."""

    def __init__(self, iomap: IoMap) -> None:
        self.iomap = iomap
        self.inputs = Inputs(
            di=dict.fromkeys(iomap.channels(DIGITAL_INPUTS), False),
            ai=dict.fromkeys(iomap.channels(ANALOG_INPUTS), 0),
        )
        self.outputs = Outputs(ro=dict.fromkeys(iomap.channels(RELAY_OUTPUTS), False))

    def all_outputs_off(self) -> None:
        for ch in self.outputs.ro:
            self.outputs.ro[ch] = False
        self.outputs.pump = False if self.iomap.charge_pump is not None else None


@dataclass(frozen=True, slots=True)
class _Point:
    """One logical IO point: its signal's name, the channel it is wired to, the image."""

    name: str
    channel: str
    image: ProcessImage


@dataclass(frozen=True, slots=True)
class DI(_Point):
    """A digital input."""

    kind = IoKind.DI

    @property
    def value(self) -> bool:
        return self.image.inputs.di[self.channel]


@dataclass(frozen=True, slots=True)
class AI(_Point):
    """An analog input in raw counts."""

    kind = IoKind.AI

    @property
    def value(self) -> int:
        return self.image.inputs.ai[self.channel]


@dataclass(frozen=True, slots=True)
class RO(_Point):
    """A relay output; setting it changes the image, the HAL writes it at the cycle's end."""

    kind = IoKind.RO

    @property
    def value(self) -> bool:
        return self.image.outputs.ro[self.channel]

    def set(self, on: bool) -> None:
        self.image.outputs.ro[self.channel] = on


class IoPoints:
    """Every logical IO point of the ride, typed and bound to one process image."""

    def __init__(self, image: ProcessImage) -> None:
        m = image.iomap
        self.image = image
        self.rotate_home = DI(Signal.ROTATE_HOME, m.rotate_home, image)
        self.tilt_home = DI(Signal.TILT_HOME, m.tilt_home, image)
        self.estop = DI(Signal.ESTOP, m.estop, image)
        self.tilt_position = AI(Signal.TILT_POSITION, m.tilt_position, image)
        self.rotate_relay = RO(Signal.ROTATE_RELAY, m.rotate_relay, image)
        self.rotate_dir = RO(Signal.ROTATE_DIR, m.rotate_dir, image)
        self.tilt_relay = RO(Signal.TILT_RELAY, m.tilt_relay, image)
        self.tilt_dir = RO(Signal.TILT_DIR, m.tilt_dir, image)

    def all(self) -> tuple[DI | AI | RO, ...]:
        return (
            self.rotate_home,
            self.tilt_home,
            self.estop,
            self.tilt_position,
            self.rotate_relay,
            self.rotate_dir,
            self.tilt_relay,
            self.tilt_dir,
        )


class IoChanges:
    """The IO points worth publishing: each one that changed since it was last published, an
    analog one only past the deadband; every point the first time."""

    def __init__(self, points: IoPoints) -> None:
        self.points = points
        self._last: dict[str, bool | int] = {}
        self._seen: tuple[int, dict[str, bool], dict[str, int], dict[str, bool]] | None = None

    def since_last(self, deadband: int, wall: float) -> list[IoValue]:
        image = self.points.image
        seen = (deadband, image.inputs.di, image.inputs.ai, image.outputs.ro)
        if seen == self._seen:
            return []  # image and deadband as last cycle's, which published what changed
        self._seen = (deadband, dict(seen[1]), dict(seen[2]), dict(seen[3]))
        last = self._last
        out: list[IoValue] = []
        for point in self.points.all():
            value = point.value
            prev = last.get(point.name)
            if prev is not None:
                if isinstance(point, AI):
                    if abs(int(value) - int(prev)) <= deadband:
                        continue
                elif value == prev:
                    continue
            last[point.name] = value
            out.append(
                IoValue(
                    name=point.name, kind=point.kind, channel=point.channel, value=value, time=wall
                )
            )
        return out
