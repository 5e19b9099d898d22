"""The RevPi backend against a process-image file and the piCtory fixture (no hardware)."""

from __future__ import annotations

import itertools
import threading
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from ride_machine.hal.base import Hal, HalError, Outputs
from ride_machine.hal.iomap import DIGITAL_INPUTS, RELAY_OUTPUTS, IoMap, Signal
from ride_machine.hal.revpi import RevPiHal, check_revpi_io
from ride_machine.schema.commands import Command, CommandRequest, Reply, StartRequest
from ride_machine.schema.findings import Severity
from ride_machine.schema.status import MachineState
from ride_machine.service.config.model import MachineConfig
from ride_machine.service.core.scan.machine import Machine
from ride_machine.service.core.scan.tasks import PendingCommand
from ride_machine.sim.procimg import ProcImgSim
from tests.fixtures.revpi import (
    CONFIG_RSC,
    address,
    load,
    make_image,
    read_bit,
    read_word,
    write_bit,
    write_word,
)
from tests.rig import FakeClock

CONFIG = str(CONFIG_RSC)
MAP = IoMap()


@pytest.fixture
def hal(image: str) -> Iterator[RevPiHal]:
    h = RevPiHal(MAP, image, CONFIG)
    yield h
    h.close()


def relay_byte(image: str) -> int:
    byte, _ = address("O_1")
    return Path(image).read_bytes()[byte]


# -- the layout ---------------------------------------------------------------------------
def test_fixture_has_the_real_product_layout() -> None:
    # Core (11 bytes) at 0, DIO at 11 (I_x at +0, O_x at +70), AIO at 124: see docs/revpi.md.
    assert [address(f"I_{n}") for n in (1, 2, 3)] == [(11, 0), (11, 1), (11, 2)]
    assert [address(f"O_{n}") for n in (1, 2, 3, 4)] == [(81, 0), (81, 1), (81, 2), (81, 3)]
    assert address("InputValue_1") == (124, None)
    types = {d["name"]: int(d["productType"]) for d in load()["Devices"]}
    assert types == {"core": 95, "dio": 96, "aio": 103}


def test_default_iomap_resolves_with_only_the_shared_module_warning(image: str) -> None:
    findings = check_revpi_io(MAP, CONFIG, image)
    assert [(f.category, f.severity, f.path) for f in findings] == [
        ("io_shared", Severity.WARNING, "/hal/iomap/rotateRelay")
    ]
    assert "O_5, O_6, O_7, O_8 share byte 81 with O_1, O_2, O_3, O_4" in findings[0].message
    assert "never writes O_9" in findings[0].message


def test_revpi_hal_is_a_hal(hal: RevPiHal) -> None:
    assert isinstance(hal, Hal)


# -- round trips through the file ---------------------------------------------------------
@pytest.mark.parametrize("signal", DIGITAL_INPUTS)
def test_each_digital_input_is_read_from_its_bit(hal: RevPiHal, image: str, signal: Signal) -> None:
    channel = MAP.channel(signal)
    write_bit(image, channel, True)
    di = hal.scan_inputs().di
    assert di[channel] is True
    assert [ch for ch, on in di.items() if on] == [channel]
    write_bit(image, channel, False)
    assert hal.scan_inputs().di[channel] is False


def test_neighbouring_bits_do_not_leak_into_inputs(hal: RevPiHal, image: str) -> None:
    byte, _ = address("I_1")
    for other in ("I_4", "I_5", "I_6", "I_7", "I_8", "I_9", "I_16"):
        write_bit(image, other, True)
    assert Path(image).read_bytes()[byte] == 0b1111_1000
    assert not any(hal.scan_inputs().di.values())


@pytest.mark.parametrize("raw", [0, 1, 1680, -1, -32768, 32767])
def test_analog_input_is_a_signed_little_endian_word(hal: RevPiHal, image: str, raw: int) -> None:
    write_word(image, "InputValue_1", raw)
    write_word(image, "InputValue_2", 999)  # the next word must not bleed in
    assert hal.scan_inputs().ai == {"InputValue_1": raw}


@pytest.mark.hazard("H48")
@pytest.mark.parametrize("signal", RELAY_OUTPUTS)
def test_each_relay_is_written_to_its_bit_and_nothing_else(
    hal: RevPiHal, image: str, signal: Signal
) -> None:
    channel = MAP.channel(signal)
    before = Path(image).read_bytes()
    hal.scan_outputs(Outputs(ro={channel: True}))
    after = Path(image).read_bytes()
    byte, bit = address(channel)
    assert bit is not None
    assert after[byte] == 1 << bit
    assert read_bit(image, channel) is True
    assert [i for i in range(len(after)) if after[i] != before[i]] == [byte]
    hal.scan_outputs(Outputs(ro={channel: False}))
    assert Path(image).read_bytes() == before


def test_a_channel_missing_from_outputs_is_written_off(hal: RevPiHal, image: str) -> None:
    hal.scan_outputs(Outputs(ro={"O_1": True, "O_3": True}))
    assert relay_byte(image) == 0b0101
    hal.scan_outputs(Outputs(ro={"O_3": True}))
    assert relay_byte(image) == 0b0100


def test_outputs_do_not_overwrite_inputs(hal: RevPiHal, image: str) -> None:
    write_bit(image, "I_2", True)
    write_word(image, "InputValue_1", -77)
    hal.scan_outputs(Outputs(ro=dict.fromkeys(MAP.channels(RELAY_OUTPUTS), True)))
    assert read_bit(image, "I_2") is True
    assert read_word(image, "InputValue_1") == -77
    assert relay_byte(image) == 0b1111


# -- safe outputs -------------------------------------------------------------------------
def test_open_drops_our_relays_and_writes_nothing_else(tmp_path: Path) -> None:
    image = make_image(tmp_path, fill=0xFF)  # every output "on" before we start
    before = Path(image).read_bytes()
    h = RevPiHal(MAP, image, CONFIG)
    try:
        after = Path(image).read_bytes()
        byte, _ = address("O_1")
        assert after[byte] == 0b1111_0000  # O_1..O_4 off; O_5..O_8 are not ours: kept
        assert [i for i in range(len(after)) if after[i] != before[i]] == [byte]
    finally:
        h.close()
    assert Path(image).read_bytes()[byte] == 0b1111_0000


def test_close_leaves_outputs_safe_and_can_repeat(hal: RevPiHal, image: str) -> None:
    hal.scan_outputs(Outputs(ro={"O_1": True, "O_2": True}))
    hal.close()
    assert relay_byte(image) == 0
    hal.close()
    with pytest.raises(HalError, match="closed"):
        hal.scan_inputs()
    with pytest.raises(HalError, match="closed"):
        hal.scan_outputs(Outputs(ro={"O_1": True}))
    assert relay_byte(image) == 0


def test_force_safe_works_after_close(hal: RevPiHal, image: str) -> None:
    hal.close()
    write_bit(image, "O_1", True)  # someone else switched it on
    hal.force_all_outputs_safe()
    assert relay_byte(image) == 0


def test_force_safe_works_when_revpimodio_is_broken(hal: RevPiHal, image: str) -> None:
    hal.scan_outputs(Outputs(ro={"O_1": True, "O_3": True}))
    hal._rpi._myfh.close()  # revpimodio2's IO path is dead (handle closed)
    with pytest.raises(HalError, match="cannot read"):
        hal.scan_inputs()
    hal.force_all_outputs_safe()  # our own descriptor still reaches the image
    assert relay_byte(image) == 0


def test_force_safe_does_not_wait_for_a_stuck_scan(hal: RevPiHal, image: str) -> None:
    hal.scan_outputs(Outputs(ro={"O_2": True}))
    hal._lock.acquire()  # a scan thread stuck in the middle of its write
    try:
        done = threading.Event()
        t = threading.Thread(target=lambda: (hal.force_all_outputs_safe(), done.set()))
        t.start()
        t.join(timeout=10)
        assert done.is_set()
    finally:
        hal._lock.release()
    assert relay_byte(image) == 0


@pytest.mark.hazard("H11")
@pytest.mark.parametrize("active_low", [True, False])
def test_read_estop_reads_the_image_and_honours_active_low(image: str, active_low: bool) -> None:
    h = RevPiHal(IoMap(estop_active_low=active_low), image, CONFIG)
    try:
        write_bit(image, "I_3", True)
        assert h.read_estop() is (not active_low)
        write_bit(image, "I_3", False)
        assert h.read_estop() is active_low
    finally:
        h.close()


def test_read_estop_follows_a_remapped_bit(tmp_path: Path) -> None:
    image = make_image(tmp_path)
    h = RevPiHal(IoMap(estop="I_12"), image, CONFIG)  # bit 11: the DIO's second byte
    try:
        write_bit(image, "I_12", True)
        assert h.read_estop() is False
        assert h.scan_inputs().di["I_12"] is True
        write_bit(image, "I_12", False)
        write_bit(image, "I_4", True)  # same bit number in the first byte: must not count
        assert h.read_estop() is True
    finally:
        h.close()


def test_truncated_image_is_an_error_not_garbage(hal: RevPiHal, image: str) -> None:
    with open(image, "r+b") as fh:
        fh.truncate(100)
    with pytest.raises(HalError, match="shorter"):
        hal.scan_inputs()


# -- a whole session through the file -----------------------------------------------------
_ids = itertools.count(1)


class RevPiRide:
    """The machine on `RevPiHal`, with `ProcImgSim` as the world, on one fake clock."""

    def __init__(
        self,
        directory: Path,
        iomap: IoMap = MAP,
        configrsc: str = CONFIG,
        physics: dict[str, float] | None = None,
    ) -> None:
        hal = {"iomap": iomap.model_dump(), "sim": physics or {}}
        self.config = MachineConfig().with_overrides(hal=hal)
        self.image = make_image(directory)
        self.clock = FakeClock()
        self.period = self.config.loop.period_s
        iomap = self.config.hal.iomap
        self.sim = ProcImgSim(iomap, self.image, configrsc, self.clock, self.config.hal.sim)
        self.hal = RevPiHal(iomap, self.image, configrsc)
        self.machine = Machine(self.config, self.hal, now=self.clock(), on_transition=None)
        self.loop = self.machine.loop
        self.state_machine = self.machine.state_machine

    @property
    def state(self) -> MachineState:
        return self.state_machine.state

    def step(self) -> None:
        self.clock.advance(self.period)
        self.sim.step()
        self.loop.step(self.clock())

    def send(self, command: Command) -> Reply:
        model = StartRequest if command is Command.START else CommandRequest
        request = model.model_validate({"transaction_id": f"r{next(_ids)}"})
        got: list[Reply] = []
        self.loop.inbox.put(PendingCommand(command, request, got.append))
        self.loop.service_inbox(self.clock())
        assert len(got) == 1
        return got[0]

    def run_until(self, pred: Callable[[], bool], max_s: float = 120.0) -> None:
        for _ in range(int(max_s / self.period)):
            if pred():
                return
            self.step()
        raise AssertionError(f"not reached in {max_s} s; state {self.state}")

    def close(self) -> None:
        self.hal.close()
        self.sim.close()


@pytest.fixture
def ride(tmp_path: Path) -> Iterator[RevPiRide]:
    r = RevPiRide(tmp_path)
    yield r
    r.close()


def _finish(ride: RevPiRide, command: Command, busy: MachineState) -> None:
    assert ride.send(command).success
    ride.run_until(lambda: ride.state is not busy)


def test_full_session_through_the_process_image(ride: RevPiRide) -> None:
    ride.step()
    assert ride.state is not MachineState.FAULT_ESTOP  # the sim wrote a released E-stop
    _finish(ride, Command.CALIBRATE_TILT, MachineState.CALIBRATING)
    _finish(ride, Command.CALIBRATE_ROTATE, MachineState.CALIBRATING)
    assert ride.state_machine.calibration.complete, ride.state
    _finish(ride, Command.HOME, MachineState.HOMING)
    assert ride.state is MachineState.IDLE, ride.state_machine.fault
    revs_before = ride.sim.world.revolutions
    assert ride.send(Command.START).success
    seen_on: set[str] = set()

    def done() -> bool:
        seen_on.update(ch for ch, on in ride.sim.relays().items() if on)
        return ride.state in (MachineState.DONE, MachineState.FAULT_HW)

    ride.run_until(done)
    assert ride.state is MachineState.DONE, ride.state_machine.fault
    # The default session (tilt to 45°, three revolutions CW) happened in the physics.
    assert ride.sim.world.tilt_deg == pytest.approx(45.0, abs=ride.config.tilt.tolerance_deg)
    assert ride.sim.world.revolutions - revs_before == pytest.approx(3.0, abs=0.1)
    assert {"O_1", "O_3", "O_4"} <= seen_on  # rotate relay, tilt relay, tilt up
    assert relay_byte(ride.image) == 0
    assert ride.hal.read_estop() is False


def test_a_seat_below_its_switch_calibrates_to_the_true_zero_through_the_image(
    tmp_path: Path,
) -> None:
    """Issue 37: from a -5° rest (the switch already closed) the offset came out 994 for 1200.
    Backed off, then latched at the edge approached from above, through the process image."""
    ride = RevPiRide(tmp_path, physics={"start_tilt_deg": -5.0, "tilt_home_hysteresis_deg": 0.5})
    try:
        ride.step()
        assert ride.sim.world.tilt_switch.closed
        _finish(ride, Command.CALIBRATE_TILT, MachineState.CALIBRATING)
        tilt = ride.state_machine.calibration.tilt
        assert tilt is not None, ride.state_machine.fault
        p = ride.config.hal.sim
        assert abs(tilt.offset_counts - p.ai_offset_counts) / p.ai_gain_counts_per_deg <= 0.25
    finally:
        ride.close()


def test_estop_drops_the_relays_in_the_same_cycle(ride: RevPiRide) -> None:
    ride.step()
    _finish(ride, Command.CALIBRATE_TILT, MachineState.CALIBRATING)
    _finish(ride, Command.CALIBRATE_ROTATE, MachineState.CALIBRATING)
    _finish(ride, Command.HOME, MachineState.HOMING)
    assert ride.send(Command.START).success
    ride.run_until(lambda: relay_byte(ride.image) & 0b0001 != 0)  # rotating
    assert ride.state is MachineState.RUNNING
    ride.sim.ride.press_estop()
    ride.step()  # one cycle: the sim writes the pressed E-stop, the loop sees it
    assert read_bit(ride.image, "I_3") is False  # normally closed: pressed reads low
    assert ride.state is MachineState.FAULT_ESTOP
    assert relay_byte(ride.image) == 0
    assert ride.hal.read_estop() is True
    for _ in range(50):  # and they stay off while it is pressed
        ride.step()
        assert relay_byte(ride.image) == 0


@pytest.mark.hazard("H43")
def test_machine_start_up_forces_outputs_safe(tmp_path: Path) -> None:
    image = make_image(tmp_path)
    write_bit(image, "O_1", True)
    write_bit(image, "O_3", True)
    h = RevPiHal(MAP, image, CONFIG)
    try:
        assert relay_byte(image) == 0
    finally:
        h.close()


# -- the hardware watchdog ----------------------------------------------------------------------
def _led(image: str) -> int:
    byte, _ = address("RevPiLED")
    return Path(image).read_bytes()[byte]


def _set_led(image: str, value: int) -> None:
    byte, _ = address("RevPiLED")
    data = bytearray(Path(image).read_bytes())
    data[byte] = value
    Path(image).write_bytes(bytes(data))


@pytest.mark.hazard("H44")
def test_the_hardware_watchdog_bit_flips_from_the_scan_and_only_it(
    image: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr("ride_machine.hal.revpi.WD_TOGGLE_S", 0.0)  # every scan, for the test
    _set_led(image, 0b0000_0101)  # LEDs A1, A2 green: another program's bits
    h = RevPiHal(MAP, image, CONFIG, hw_watchdog=True)
    try:
        seen = []
        for _ in range(4):
            h.scan_outputs(Outputs())
            seen.append(_led(image))
        assert [b >> 7 for b in seen] == [1, 0, 1, 0]
        assert all(b & 0x7F == 0b0000_0101 for b in seen)
        h.force_all_outputs_safe()  # the safe image is the relays; the watchdog bit is not one
        assert _led(image) == seen[-1]
    finally:
        h.close()


def test_the_hardware_watchdog_bit_is_never_written_unless_asked(
    image: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr("ride_machine.hal.revpi.WD_TOGGLE_S", 0.0)
    h = RevPiHal(MAP, image, CONFIG)
    try:
        for _ in range(3):
            h.scan_outputs(Outputs())
        assert _led(image) == 0
    finally:
        h.close()


def test_energised_reads_the_relays_from_the_image(hal: RevPiHal, image: str) -> None:
    assert not hal.energised()
    hal.scan_outputs(Outputs(ro={"O_1": True}))
    assert hal.energised()
    hal.force_all_outputs_safe()
    assert not hal.energised()
