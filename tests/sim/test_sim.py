"""The simulator HAL: physics of both axes, the E-stop, and every fault injection."""

from __future__ import annotations

import itertools
from collections.abc import Callable

import pytest

from ride_machine.hal.base import Hal, Outputs
from ride_machine.hal.iomap import RELAY_OUTPUTS, IoMap, Signal
from ride_machine.sim.hal import SimHal
from ride_machine.sim.physics import SwitchFault, World
from ride_machine.sim.settings import PhysicsParams
from tests.rig import FakeClock

DT = 0.01
PARAMS = PhysicsParams()


class Sim:
    """A SimHal with named relays and a fake clock, for driving the physics directly."""

    def __init__(self, params: PhysicsParams = PARAMS, iomap: IoMap | None = None) -> None:
        self.clock = FakeClock()
        self.hal = SimHal(self.clock, iomap or IoMap(), params)
        self.m = self.hal.iomap
        self.drive: dict[Signal, bool] = dict.fromkeys(RELAY_OUTPUTS, False)

    def set(self, **relays: bool) -> None:
        names = {"rotate": Signal.ROTATE_RELAY, "rotate_ccw": Signal.ROTATE_DIR,
                 "tilt": Signal.TILT_RELAY, "tilt_up": Signal.TILT_DIR}  # fmt: skip
        for key, on in relays.items():
            self.drive[names[key]] = on
        self.hal.scan_outputs(Outputs(ro={self.m.channel(s): v for s, v in self.drive.items()}))

    def run(self, seconds: float) -> list[dict[str, bool | int]]:
        """Scan for `seconds` of simulated time; every scan's inputs by logical name."""
        out = []
        for _ in range(round(seconds / DT)):
            self.clock.advance(DT)
            inputs = self.hal.scan_inputs()
            out.append(
                {
                    "rotate_home": inputs.di[self.m.rotate_home],
                    "tilt_home": inputs.di[self.m.tilt_home],
                    "estop": inputs.di[self.m.estop],
                    "tilt_raw": inputs.ai[self.m.tilt_position],
                }
            )
        return out

    @property
    def world(self) -> World:
        return self.hal.world


def rising_edges(values: list[bool | int]) -> int:
    return sum(1 for a, b in itertools.pairwise(values) if b and not a)


def test_sim_implements_the_hal_protocol() -> None:
    assert isinstance(Sim().hal, Hal)


def test_starts_with_every_output_safe_and_the_configured_positions() -> None:
    sim = Sim()
    assert not sim.hal.outputs.any_on()
    assert set(sim.hal.outputs.ro) == set(IoMap().channels(RELAY_OUTPUTS))
    assert sim.world.rotate_deg == PARAMS.start_rotate_deg
    assert sim.world.tilt_deg == PARAMS.start_tilt_deg


@pytest.mark.parametrize(("ccw", "sign"), [(False, 1.0), (True, -1.0)], ids=["cw", "ccw"])
def test_rotate_turns_at_its_speed_in_the_driven_direction(ccw: bool, sign: float) -> None:
    sim = Sim()
    sim.set(rotate=True, rotate_ccw=ccw)
    sim.run(2.0)
    assert sim.world.rotate_travel_deg == pytest.approx(sign * 2.0 * PARAMS.rotate_speed_dps)
    expected = (PARAMS.start_rotate_deg + sign * 180.0) % 360.0
    assert sim.world.rotate_deg == pytest.approx(expected)
    assert sim.world.revolutions == pytest.approx(sign * 0.5)


def test_rotate_stands_still_without_its_relay() -> None:
    sim = Sim()
    sim.set(rotate_ccw=True)  # direction alone moves nothing
    sim.run(3.0)
    assert sim.world.rotate_travel_deg == 0.0


def test_rotate_home_closes_once_per_revolution_for_its_arc() -> None:
    params = PhysicsParams(rotate_speed_dps=90.0, home_arc_deg=18.0)
    sim = Sim(params)
    sim.set(rotate=True)
    home = [s["rotate_home"] for s in sim.run(40.0)]  # ten revolutions
    assert isinstance(home[0], bool)
    assert rising_edges(home) == 10
    closed_s = sum(home) * DT
    assert closed_s == pytest.approx(10 * 18.0 / 90.0, abs=10 * DT)


def test_home_switch_opens_and_closes_at_the_arc_edges() -> None:
    sim = Sim(PhysicsParams(start_rotate_deg=350.0, home_arc_deg=10.0))
    assert not sim.world.sense().rotate_home
    sim.set(rotate=True)
    sim.run(10.5 / PARAMS.rotate_speed_dps)  # to 0.5°
    assert sim.world.sense().rotate_home
    sim.run(10.0 / PARAMS.rotate_speed_dps)  # to 10.5°
    assert not sim.world.sense().rotate_home


def test_tilt_moves_at_its_speed_and_stops_at_its_limits() -> None:
    sim = Sim()
    sim.set(tilt=True, tilt_up=True)
    sim.run(2.0)
    assert sim.world.tilt_deg == pytest.approx(PARAMS.start_tilt_deg + 2.0 * PARAMS.tilt_speed_dps)
    sim.run(20.0)
    assert sim.world.tilt_deg == PARAMS.tilt_max_deg
    sim.set(tilt_up=False)
    sim.run(20.0)
    assert sim.world.tilt_deg == PARAMS.tilt_min_deg


def test_tilt_analog_input_is_offset_plus_gain_times_degrees() -> None:
    params = PhysicsParams(ai_offset_counts=900.0, ai_gain_counts_per_deg=25.0, start_tilt_deg=0.0)
    sim = Sim(params)
    sim.set(tilt=True, tilt_up=True)
    readings = sim.run(3.0)
    for k, sample in enumerate(readings, start=1):
        degrees = PARAMS.tilt_speed_dps * k * DT
        assert sample["tilt_raw"] == pytest.approx(900.0 + 25.0 * degrees, abs=1)
    assert sim.world.tilt_deg == pytest.approx(45.0)


def test_analog_input_is_clamped_to_int16() -> None:
    sim = Sim(PhysicsParams(ai_offset_counts=40000.0))
    assert sim.run(DT)[-1]["tilt_raw"] == 32767


def test_tilt_home_closes_at_zero_degrees() -> None:
    sim = Sim(PhysicsParams(start_tilt_deg=1.0))
    sim.set(tilt=True)
    before = [s["tilt_home"] for s in sim.run(1.0 / PARAMS.tilt_speed_dps - 2 * DT)]
    assert not any(before)
    assert sim.run(3 * DT)[-1]["tilt_home"]
    assert sim.world.tilt_deg <= 0.0


def test_motion_is_integrated_under_the_outputs_that_were_on() -> None:
    """A write first accounts for the time the old outputs were on, then applies the new ones."""
    sim = Sim()
    sim.set(rotate=True)
    sim.clock.advance(0.05)
    sim.set(rotate=False)
    assert sim.world.rotate_travel_deg == pytest.approx(0.05 * PARAMS.rotate_speed_dps)
    sim.clock.advance(1.0)
    sim.run(DT)
    assert sim.world.rotate_travel_deg == pytest.approx(0.05 * PARAMS.rotate_speed_dps)


@pytest.mark.hazard("H11")
def test_estop_cuts_all_motion_and_reads_as_an_open_safety_circuit() -> None:
    sim = Sim()
    sim.set(rotate=True, tilt=True, tilt_up=True)
    assert sim.run(DT)[-1]["estop"] is True  # normally closed: released reads high
    sim.hal.press_estop()
    where = (sim.world.rotate_travel_deg, sim.world.tilt_deg)
    readings = sim.run(2.0)
    assert all(s["estop"] is False for s in readings)
    assert sim.hal.read_estop()
    assert (sim.world.rotate_travel_deg, sim.world.tilt_deg) == where
    sim.hal.release_estop()
    assert sim.run(DT)[-1]["estop"] is True
    assert not sim.hal.read_estop()
    # The drive is still on: motion resumes on release (it is the controller's job to stop).
    sim.run(1.0)
    assert sim.world.rotate_travel_deg > where[0]


def test_estop_polarity_follows_the_io_map() -> None:
    sim = Sim(iomap=IoMap(estop_active_low=False))
    assert sim.run(DT)[-1]["estop"] is False
    sim.hal.press_estop()
    assert sim.run(DT)[-1]["estop"] is True


def test_output_writes_keep_only_known_channels_and_default_off() -> None:
    sim = Sim()
    m = sim.m
    sim.hal.scan_outputs(Outputs(ro={m.rotate_relay: True, "O_99": True}))
    assert sim.hal.outputs.ro == {
        m.rotate_relay: True,
        m.rotate_dir: False,
        m.tilt_relay: False,
        m.tilt_dir: False,
    }
    snapshot = sim.hal.outputs
    snapshot.ro[m.tilt_relay] = True  # a copy: the HAL is not changed behind its back
    assert not sim.hal.relay(Signal.TILT_RELAY)


def test_force_safe_and_close_drop_every_output() -> None:
    sim = Sim()
    sim.set(rotate=True, rotate_ccw=True, tilt=True, tilt_up=True)
    assert all(sim.hal.outputs.ro.values())
    sim.hal.force_all_outputs_safe()
    assert not sim.hal.outputs.any_on()
    sim.set(rotate=True)
    sim.hal.close()
    assert sim.hal.closed
    assert not sim.hal.outputs.any_on()
    where = sim.world.rotate_travel_deg
    sim.run(1.0)
    assert sim.world.rotate_travel_deg == where


def test_custom_io_map_channels_are_used() -> None:
    iomap = IoMap(rotate_home="I_7", tilt_position="InputValue_3", rotate_relay="O_9")
    sim = Sim(iomap=iomap)
    inputs = sim.hal.scan_inputs()
    assert "I_7" in inputs.di
    assert "InputValue_3" in inputs.ai
    sim.hal.scan_outputs(Outputs(ro={"O_9": True}))
    assert sim.hal.relay(Signal.ROTATE_RELAY)
    assert sim.world.drive.rotate_on


def test_world_ignores_non_positive_time_steps() -> None:
    world = World()
    world.drive.rotate_on = True
    world.step(0.0)
    world.step(-1.0)
    assert world.rotate_travel_deg == 0.0
    assert world.time == 0.0


def world_state(world: World) -> tuple[object, ...]:
    """Everything about a simulated world, the noise generator's state included."""
    return (
        world.time,
        world.rotate_deg,
        world.rotate_travel_deg,
        world.tilt_deg,
        world.faults,
        world.drive,
        world.params,
        world._frozen_raw,
        world._rng.getstate(),
    )


class StillTwins:
    """Two simulators in lockstep: `fast` reuses its image while the world is still, `full`
    senses every scan. Every scan's image and the whole world must be the same in both."""

    def __init__(self) -> None:
        self.full, self.fast = Sim(), Sim()
        self.full.hal.still_scans = False
        self.sims = (self.full, self.fast)

    def both(self, act: Callable[[Sim], object]) -> None:
        for sim in self.sims:
            act(sim)

    def run(self, seconds: float) -> int:
        """Scan both for `seconds`, comparing after each scan; the scans `fast` reused."""
        before = self.fast.hal.reused
        full, fast = self.full.run(seconds), self.fast.run(seconds)
        assert fast == full
        assert world_state(self.fast.world) == world_state(self.full.world)
        assert self.full.hal.reused == 0
        return self.fast.hal.reused - before


STILL_SCANS = round(0.5 / DT)


def push_tilt(sim: Sim) -> None:
    sim.world.tilt_deg += 3.0  # by hand: no relay, no noise


@pytest.mark.parametrize(
    "change",
    [
        lambda sim: sim.set(rotate=True),
        lambda sim: sim.set(tilt=True, tilt_up=True),
        push_tilt,
        lambda sim: setattr(sim.world, "rotate_deg", 5.0),  # onto the home switch
        lambda sim: sim.hal.press_estop(),
        lambda sim: sim.hal.stick_home("rotate", SwitchFault.STUCK_CLOSED),
        lambda sim: sim.hal.stick_home("tilt", SwitchFault.STUCK_CLOSED),
        lambda sim: sim.hal.set_tilt_noise(40.0),
        lambda sim: setattr(
            sim.world, "params", PhysicsParams(ai_offset_counts=PARAMS.ai_offset_counts + 100)
        ),
    ],
    ids=[
        "rotate",
        "tilt",
        "tilt-by-hand",
        "rotate-by-hand",
        "estop",
        "rotate-stuck",
        "tilt-stuck",
        "noise",
        "params",
    ],
)
def test_a_still_world_reuses_its_image_and_a_change_is_sensed(
    change: Callable[[Sim], None],
) -> None:
    twins = StillTwins()
    assert twins.run(0.5) >= STILL_SCANS - 1
    twins.both(change)
    moving = twins.fast.world.still() is None  # a relay on or noise: sensed every scan
    reused = twins.run(1.0)
    assert reused == 0 if moving else reused >= round(1.0 / DT) - 1
    twins.both(lambda sim: sim.set(rotate=False, tilt=False))
    twins.both(lambda sim: sim.hal.clear_faults())
    twins.both(lambda sim: sim.hal.release_estop())
    assert twins.run(0.5) >= STILL_SCANS - 1


def test_a_frozen_input_reads_the_tilt_again_once_thawed() -> None:
    twins = StillTwins()
    twins.both(lambda sim: sim.hal.freeze_tilt_ai())
    twins.run(0.2)
    twins.both(push_tilt)  # frozen: the image keeps the old value
    twins.run(0.2)
    held = twins.fast.run(DT)[-1]["tilt_raw"]
    twins.full.run(DT)
    twins.both(lambda sim: sim.hal.freeze_tilt_ai(False))
    twins.run(0.2)
    assert twins.fast.run(DT)[-1]["tilt_raw"] > held
    twins.full.run(DT)
    twins.run(0.2)


def test_a_still_world_still_counts_its_time() -> None:
    twins = StillTwins()
    start = twins.fast.world.time
    assert twins.run(1.0) >= round(1.0 / DT) - 1
    assert twins.fast.world.time == pytest.approx(start + 1.0)
