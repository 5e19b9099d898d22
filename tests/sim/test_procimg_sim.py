"""The process-image simulator: relays read from the file, sensors written into it."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from ride_machine.hal.base import HalError, Outputs
from ride_machine.hal.iomap import IoMap
from ride_machine.hal.revpi import RevPiConfigError, RevPiHal
from ride_machine.sim.physics import SwitchFault
from ride_machine.sim.procimg import ProcImgSim
from ride_machine.sim.settings import PhysicsParams
from tests.fixtures.revpi import (
    CONFIG_RSC,
    address,
    read_bit,
    read_word,
    write_bit,
)
from tests.rig import FakeClock

CONFIG = str(CONFIG_RSC)
PARAMS = PhysicsParams()  # starts at rotate 137°, tilt 12°: neither switch closed


@pytest.fixture
def clock() -> FakeClock:
    return FakeClock()


@pytest.fixture
def sim(image: str, clock: FakeClock) -> Iterator[ProcImgSim]:
    s = ProcImgSim(IoMap(), image, CONFIG, clock, PARAMS)
    yield s
    s.close()


def raw_tilt(deg: float) -> int:
    return round(PARAMS.ai_offset_counts + PARAMS.ai_gain_counts_per_deg * deg)


def test_sensors_are_in_the_image_as_soon_as_it_starts(sim: ProcImgSim, image: str) -> None:
    assert read_bit(image, "I_3") is True  # E-stop released: a normally closed contact reads high
    assert read_bit(image, "I_1") is False  # rotate at 137°: off its home cam
    assert read_bit(image, "I_2") is False  # tilt at 12°: above home
    assert read_word(image, "InputValue_1") == raw_tilt(12.0)


def test_relays_from_the_image_drive_the_physics(
    sim: ProcImgSim, image: str, clock: FakeClock
) -> None:
    write_bit(image, "O_1", True)  # rotate relay, direction CW (O_2 off)
    sim.step()  # picks the relay up at this moment
    clock.advance(0.05)
    sim.step()
    assert sim.world.rotate_deg == pytest.approx(137.0 + 0.05 * PARAMS.rotate_speed_dps)
    assert sim.relays()["O_1"] is True


def test_a_relay_counts_from_the_step_that_saw_it(
    sim: ProcImgSim, image: str, clock: FakeClock
) -> None:
    # The loop writes at t0, the sim's next step is at t0 + dt: the axis moved the whole dt.
    write_bit(image, "O_3", True)  # tilt relay
    write_bit(image, "O_4", True)  # tilt up
    clock.advance(0.05)
    sim.step()
    assert sim.world.tilt_deg == pytest.approx(12.0 + 0.05 * PARAMS.tilt_speed_dps)
    assert read_word(image, "InputValue_1") == raw_tilt(12.0 + 0.05 * PARAMS.tilt_speed_dps)


def test_home_switches_close_in_the_image(sim: ProcImgSim, image: str, clock: FakeClock) -> None:
    write_bit(image, "O_3", True)  # tilt down to home
    for _ in range(200):
        clock.advance(0.01)
        sim.step()
    assert read_bit(image, "I_2") is True
    write_bit(image, "O_3", False)
    write_bit(image, "O_1", True)  # rotate CW until the cam at 0°
    deg_to_home = 360.0 - 137.0
    for _ in range(int(deg_to_home / PARAMS.rotate_speed_dps / 0.01) + 2):
        clock.advance(0.01)
        sim.step()
    assert read_bit(image, "I_1") is True


def test_injected_faults_reach_the_image(sim: ProcImgSim, image: str) -> None:
    sim.ride.press_estop()
    sim.ride.stick_home("rotate", SwitchFault.STUCK_CLOSED)
    sim.step()
    assert read_bit(image, "I_3") is False
    assert read_bit(image, "I_1") is True
    sim.ride.release_estop()
    sim.ride.clear_faults()
    sim.step()
    assert read_bit(image, "I_3") is True
    assert read_bit(image, "I_1") is False


def test_estop_active_high_wiring_is_written_as_such(image: str, clock: FakeClock) -> None:
    with ProcImgSim(IoMap(estop_active_low=False), image, CONFIG, clock) as s:
        assert read_bit(image, "I_3") is False
        s.ride.press_estop()
        s.step()
        assert read_bit(image, "I_3") is True


def test_sim_and_hal_each_write_only_their_own_bytes(
    sim: ProcImgSim, image: str, clock: FakeClock
) -> None:
    hal = RevPiHal(IoMap(), image, CONFIG)
    try:
        sensors = Path(image).read_bytes()
        hal.scan_outputs(Outputs(ro={"O_1": True, "O_4": True}))
        after = Path(image).read_bytes()
        changed = [i for i in range(len(after)) if after[i] != sensors[i]]
        assert changed == [address("O_1")[0]]
        sim.step()
        assert hal.scan_inputs().ai == {"InputValue_1": raw_tilt(12.0)}
        assert read_bit(image, "O_1") is True  # the sim left the relays alone
        assert sim.relays() == {"O_1": True, "O_2": False, "O_3": False, "O_4": True}
    finally:
        hal.close()


def test_remapped_channels_are_followed(image: str, clock: FakeClock) -> None:
    iomap = IoMap.model_validate({"estop": "I_16", "rotateRelay": "O_9"})
    with ProcImgSim(iomap, image, CONFIG, clock) as s:
        assert read_bit(image, "I_16") is True
        assert read_bit(image, "I_3") is False
        write_bit(image, "O_9", True)
        s.step()
        assert s.world.drive.rotate_on is True


def test_a_map_that_does_not_fit_is_refused(image: str, clock: FakeClock) -> None:
    before = Path(image).read_bytes()
    with pytest.raises(RevPiConfigError) as exc:
        ProcImgSim(IoMap(estop="O_5"), image, CONFIG, clock)
    assert [f.path for f in exc.value.findings] == ["/hal/iomap/estop"]
    assert Path(image).read_bytes() == before


def test_a_closed_sim_refuses_to_step(sim: ProcImgSim) -> None:
    sim.close()
    with pytest.raises(HalError):
        sim.step()
