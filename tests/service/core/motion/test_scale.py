"""The tilt sensor's commissioned scale: a calibration measured on a drive off its nominal speed,
made on a home switch that moved, entered or loaded outside it, is refused; one inside it rides
no further past a target than the band allows; an inverted direction output stops within a
window even before the tilt is calibrated."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from ride_machine.schema.calibration import CalibrationSet
from ride_machine.schema.commands import Command, Session, TiltStep
from ride_machine.schema.errors import ErrorCode
from ride_machine.schema.status import FaultCode, MachineState
from ride_machine.service.config.model import MachineConfig
from ride_machine.service.core.motion.scale import scale_problem
from ride_machine.service.errors import MachineError
from tests.rig import Rig

S = MachineState
MOTION = (S.CALIBRATING, S.HOMING, S.RUNNING)
NOMINAL_DPS = MachineConfig().tilt.nominal_speed_dps


class Highest:
    """Steps `rig` until its motion ends, noting the world's highest tilt on the way."""

    def __init__(self, rig: Rig) -> None:
        self.rig, self.deg = rig, rig.hal.world.tilt_deg

    def run(self, command: Command, max_s: float = 120.0, **payload: object) -> MachineState:
        reply = self.rig.send(command, **payload)
        assert reply.success, reply

        def ended() -> bool:
            self.deg = max(self.deg, self.rig.hal.world.tilt_deg)
            return self.rig.state not in MOTION

        self.rig.run_until(ended, max_s)
        return self.rig.state


def drive_at(factor: float) -> Rig:
    """A machine whose tilt drive runs at `factor` times its nominal speed."""
    config = MachineConfig().with_overrides(hal={"sim": {"tilt_speed_dps": NOMINAL_DPS * factor}})
    return Rig(config=config)


@pytest.mark.hazard("H19")
@pytest.mark.parametrize("factor", [0.5, 0.75, 0.9, 1.1, 1.2, 1.3, 2.0])
def test_a_drive_off_its_nominal_speed_cannot_calibrate_the_tilt(factor: float) -> None:
    rig = drive_at(factor)
    top = Highest(rig)
    assert top.run(Command.CALIBRATE_TILT) is S.FAULT_HW
    fault = rig.state_machine.fault
    assert fault is not None and fault.code is FaultCode.CALIBRATION_IMPLAUSIBLE, fault
    assert "outside the sensor's commissioned 38..42" in fault.message
    assert "nominal speed" in fault.message
    assert rig.state_machine.calibration.tilt is None
    # The stroke itself is the calibration's own 2 s, at the drive's true speed.
    assert top.deg <= NOMINAL_DPS * factor * rig.config.tilt.calibration_stroke_s + 1.0


@pytest.mark.hazard("H19")
@pytest.mark.parametrize("factor", [0.96, 1.04])
def test_a_calibration_the_scale_lets_through_rides_at_most_the_band_past_a_target(
    factor: float,
) -> None:
    rig = drive_at(factor)
    rig.calibrate()
    rig.home()
    top = Highest(rig)
    session = Session(name="top", steps=[TiltStep(degrees=60.0)])
    assert top.run(Command.START, session=session.model_dump()) is S.DONE
    cfg = rig.config.tilt
    band = (cfg.gain_max_counts_per_deg - cfg.gain_min_counts_per_deg) / (
        2 * cfg.gain_min_counts_per_deg
    )
    # 60° read through a gain off by the drive's factor, within the band: ~2.4° at most here.
    assert abs(rig.hal.world.tilt_deg - 60.0) <= 60.0 * band + cfg.tolerance_deg
    assert top.deg <= 60.0 * (1 + band) + cfg.tolerance_deg


@pytest.mark.hazard("H24")
def test_a_home_switch_that_moved_is_not_baked_into_a_new_calibration() -> None:
    config = MachineConfig().with_overrides(hal={"sim": {"tilt_home_deg": 3.0}})
    rig = Rig(config=config)
    assert Highest(rig).run(Command.CALIBRATE_TILT) is S.FAULT_HW
    fault = rig.state_machine.fault
    assert fault is not None and fault.code is FaultCode.CALIBRATION_IMPLAUSIBLE, fault
    assert "outside the commissioned 1160..1240 at the home switch" in fault.message
    zero = float(fault.message.split()[2])  # "tilt zero <counts> counts is outside …"
    assert abs(zero - 1320.0) <= 10.0  # 3° of 40 counts above 1200, latched between scans
    assert rig.state_machine.calibration.tilt is None


@pytest.mark.parametrize(
    ("offset", "gain", "path"),
    [
        (1200.0, 52.0, "/tilt/gain_counts_per_deg"),  # the previous round's typed +30 %
        (1200.0, 30.0, "/tilt/gain_counts_per_deg"),
        (1200.0, 0.025, "/tilt/gain_counts_per_deg"),  # degrees per count typed
        (1400.0, 40.0, "/tilt/offset_counts"),  # the switch 5° away
    ],
)
@pytest.mark.hazard("H21")
def test_an_entry_outside_the_scale_is_refused_naming_the_field(
    offset: float, gain: float, path: str
) -> None:
    rig = Rig()
    values = CalibrationSet.model_validate(
        {"transaction_id": "t1", "tilt": {"offset_counts": offset, "gain_counts_per_deg": gain}}
    )
    with pytest.raises(MachineError) as refused:
        rig.state_machine.enter_calibration(values, rig.clock())
    assert refused.value.code is ErrorCode.PARAM_OUT_OF_RANGE
    assert refused.value.path == path
    assert rig.state_machine.calibration.tilt is None


def _file(data_dir: Path, offset: float, gain: float) -> bytes:
    data = json.dumps(
        {
            "version": 1,
            "tilt": {"offset_counts": offset, "gain_counts_per_deg": gain, "source": "measured"},
            "rotate": {"revolution_s": 4.0, "home_arc_deg": 10.0, "source": "measured"},
        }
    ).encode()
    (data_dir / "calibration.json").write_bytes(data)
    return data


@pytest.mark.hazard("H22")
def test_a_stored_tilt_calibration_outside_the_scale_is_not_used_and_the_file_is_kept(
    tmp_path: Path,
) -> None:
    data = _file(tmp_path, 1200.0, 52.0)  # trusted as measured, 30 % off
    rig = Rig(data_dir=tmp_path)
    cal = rig.state_machine.calibration
    assert cal.tilt is None and cal.rotate is not None
    assert rig.state is S.WARNING_NEEDS_CALIBRATION
    status = rig.loop.build_status(rig.clock())
    assert any("stored tilt gain 52.00 counts/° is outside" in w for w in status.warnings), status
    assert (tmp_path / "calibration.json").read_bytes() == data


@pytest.mark.hazard("H22")
def test_a_stored_calibration_inside_the_scale_is_used(tmp_path: Path) -> None:
    _file(tmp_path, 1201.0, 40.2)
    rig = Rig(data_dir=tmp_path)
    tilt = rig.state_machine.calibration.tilt
    assert tilt is not None and tilt.gain_counts_per_deg == 40.2
    assert not any("commissioned" in w for w in rig.loop.build_status(rig.clock()).warnings)


@pytest.mark.hazard("H19")
def test_an_inverted_direction_output_stops_an_uncalibrated_seek_within_a_window() -> None:
    config = MachineConfig().with_overrides(hal={"sim": {"start_tilt_deg": 12.0}})
    rig = Rig(config=config)
    world = rig.hal.world
    step = world.step

    def inverted(dt: float) -> None:  # the tilt's direction output wired the other way
        world.drive.tilt_up = not world.drive.tilt_up
        step(dt)
        world.drive.tilt_up = not world.drive.tilt_up

    world.step = inverted  # type: ignore[method-assign]
    top = Highest(rig)
    assert top.run(Command.CALIBRATE_TILT) is S.FAULT_HW
    fault = rig.state_machine.fault
    assert fault is not None and fault.code is FaultCode.TILT_NOT_FOLLOWING, fault
    window = rig.config.tilt.follow_window_s * NOMINAL_DPS
    assert top.deg <= 12.0 + window + 1.0  # one follow window of travel, not the end stop


def test_the_scale_names_the_first_value_outside_it() -> None:
    cfg = MachineConfig().tilt
    assert scale_problem(1200.0, 40.0, cfg) is None
    gain = scale_problem(1000.0, 50.0, cfg)
    assert gain is not None and gain.path == "/tilt/gain_counts_per_deg"
    zero = scale_problem(1000.0, 40.0, cfg)
    assert zero is not None and zero.path == "/tilt/offset_counts"
