"""Controllers: the `Timeout` windows they share, and what a pause does to each kind of phase."""

from __future__ import annotations

import pytest

from ride_machine.schema.commands import Command
from ride_machine.schema.status import MachineState
from ride_machine.service.core.motion.base import Chain, Timeout
from ride_machine.service.core.motion.calibrate import RotateCalibrate, TiltCalibrate, TiltCalPhase
from ride_machine.service.core.motion.homing import Phase, RotateHome
from tests.rig import Rig, known_calibration, rig_in

S = MachineState
C = Command


def test_timeout_expires_only_past_its_limit_and_is_done_at_it() -> None:
    t = Timeout(2.0)
    assert not t.started
    t.start(10.0)
    assert t.started and t.elapsed(11.5) == 1.5
    assert not t.expired(12.0) and t.done(12.0)  # a timeout needs more, a dwell is over
    assert t.expired(12.001)


def test_timeout_resume_starts_the_window_again_so_paused_time_never_counts() -> None:
    t = Timeout(1.0)
    t.start(0.0)
    t.resume(100.0)  # paused from ~0.5 to 100
    assert not t.expired(100.9)
    assert t.expired(101.1)


def test_timeout_start_can_set_a_new_limit_and_stop_disarms_it() -> None:
    t = Timeout(1.0)
    t.start(0.0, limit_s=5.0)
    assert t.limit_s == 5.0 and not t.expired(4.0)
    t.stop()
    assert not t.started
    with pytest.raises(AssertionError):
        t.elapsed(1.0)


def test_rotate_home_backs_off_the_switch_dwells_then_seeks() -> None:
    rig = rig_in(S.IDLE)  # both axes on their home switches
    seen: list[Phase] = []
    assert rig.send(C.HOME).success

    def record() -> bool:
        ctl = rig.state_machine.motion()
        if isinstance(ctl, RotateHome) and (not seen or seen[-1] is not ctl.phase):
            seen.append(ctl.phase)
        return rig.state is not S.HOMING

    rig.run_until(record)
    assert rig.state is S.IDLE, rig.state_machine.fault
    assert seen == [Phase.BACKOFF, Phase.RUNUP, Phase.DWELL, Phase.SEEK, Phase.STOPPED]


def test_a_paused_tilt_stroke_measures_again_from_home() -> None:
    rig = Rig()
    assert rig.send(C.CALIBRATE_TILT).success
    cal = rig.state_machine.context.drive.controller
    assert isinstance(cal, TiltCalibrate)
    rig.run_until(lambda: cal.phase is TiltCalPhase.STROKE)
    rig.step(20)
    assert rig.send(C.PAUSE).success
    rig.step(1000)  # far longer than any window
    assert rig.send(C.RESUME).success
    assert cal.phase is TiltCalPhase.FIRST  # the interrupted stroke is thrown away
    assert not cal.zeros
    rig.run_to_state(S.WARNING_NEEDS_CALIBRATION, S.FAULT_HW)
    assert rig.state_machine.fault is None
    tilt, expected = rig.state_machine.calibration.tilt, known_calibration().tilt
    assert tilt is not None and expected is not None
    assert tilt.gain_counts_per_deg == pytest.approx(expected.gain_counts_per_deg, rel=0.05)


def test_a_paused_rotate_measurement_measures_again_from_home() -> None:
    rig = Rig(calibration=known_calibration())
    assert rig.send(C.CALIBRATE_ROTATE).success
    chain = rig.state_machine.context.drive.controller
    assert isinstance(chain, Chain)
    rig.run_until(lambda: isinstance(chain.current, RotateCalibrate))
    cal = chain.current
    assert isinstance(cal, RotateCalibrate)
    rig.run_until(lambda: cal.homing is None)  # measuring
    rig.step(50)
    assert rig.send(C.PAUSE).success
    rig.step(1000)
    assert rig.send(C.RESUME).success
    assert cal.homing is not None
    rig.run_until(lambda: rig.state is not S.CALIBRATING)
    assert rig.state_machine.fault is None
    rotate = rig.state_machine.calibration.rotate
    expected = known_calibration().rotate
    assert rotate is not None and expected is not None
    assert rotate.revolution_s == pytest.approx(expected.revolution_s, rel=0.02)
