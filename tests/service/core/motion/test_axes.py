"""Axis positions and FastData status bits against the simulated world's truth (fake clock).

The rotate axis has no encoder: its angle is dead-reckoned from the drive time and referenced
at home-switch edges. These tests compare every record with `sim.physics.World.rotate_deg`.
"""

from __future__ import annotations

from collections.abc import Callable

import pytest

from ride_machine.schema.axes import ROTATE_AXIS_NUMBER, TILT_AXIS_NUMBER, AxisRecord, PnStatus
from ride_machine.schema.calibration import CalibrationSet, TiltCalibrationSet
from ride_machine.schema.commands import Command, Direction, RotateStep, Session, TiltStep
from ride_machine.schema.status import MachineState as S
from tests.rig import Rig, known_calibration

ROTATE_TOL_DEG = 2.0
"""The documented tracking tolerance (docs/fastdata.md): one cycle of travel plus drift."""
ROTATE_STEP_DEG = 0.9
"""One cycle's travel (90°/s, 10 ms): an edge is latched within half of it either way."""


def rotate_error(rig: Rig, record: AxisRecord) -> float:
    delta = record.position_fb - rig.hal.world.rotate_deg
    return abs((delta + 180.0) % 360.0 - 180.0)


def latest(rig: Rig, axis: str) -> AxisRecord:
    return rig.loop.published.axes[axis]


def run_checking(rig: Rig, until: Callable[[], bool], max_s: float = 60.0) -> list[AxisRecord]:
    """Step until `until()`, checking every rotate record published on the way; returns them."""
    seen: list[AxisRecord] = []
    start = len(rig.sink.axes)

    def check() -> bool:
        nonlocal start
        for rec in rig.sink.axes[start:]:
            if rec.axis == "rotate":
                seen.append(rec)
                assert rec.position_known, rec
                assert rotate_error(rig, rec) <= ROTATE_TOL_DEG, (rec, rig.hal.world.rotate_deg)
        start = len(rig.sink.axes)
        return until()

    rig.run_until(check, max_s)
    return seen


def homed_rig() -> Rig:
    rig = Rig(calibration=known_calibration())
    rig.home()
    return rig


def test_rotate_position_is_unknown_until_homed_and_says_so() -> None:
    rig = Rig(calibration=known_calibration())  # a restart: calibrated, never homed
    rec = latest(rig, "rotate")
    assert not rec.position_known
    assert rec.pn_status & PnStatus.POSITION_UNKNOWN
    assert not rec.pn_status & PnStatus.SETTLED
    assert rig.loop.published.status is not None
    assert rig.loop.published.status.rotate_deg is None
    rig.home()
    rec = latest(rig, "rotate")
    assert rec.position_known and not rec.pn_status & PnStatus.POSITION_UNKNOWN
    assert rotate_error(rig, rec) <= ROTATE_TOL_DEG
    assert rec.pn_status & PnStatus.SETTLED
    status = rig.loop.build_status(rig.clock())
    assert status.rotate_deg is not None and status.homed.rotate


def test_rotate_tracks_the_world_through_a_whole_session() -> None:
    rig = homed_rig()
    assert rig.send(Command.START).success
    seen = run_checking(rig, lambda: rig.state is S.DONE)
    moving = [r for r in seen if r.pn_status & PnStatus.MOVING]
    assert len(moving) > 100
    speed = known_calibration().rotate.speed_dps  # type: ignore[union-attr]
    assert all(abs(r.velocity_cmd - speed) < 1e-6 for r in moving)
    assert sum(abs(r.velocity_fb - speed) < 1e-6 for r in moving) >= len(moving) - 1
    # Positions cover the whole circle, not a stuck 0.0.
    assert max(r.position_fb for r in moving) > 300 and min(r.position_fb for r in moving) < 60
    end = latest(rig, "rotate")
    # Three turns from home, latched midway between the scans either side of the last edge.
    assert end.pn_status & PnStatus.SETTLED
    assert end.drive_fb == pytest.approx(3.0, abs=ROTATE_STEP_DEG / 360)


def test_rotate_tracks_across_pause_and_resume() -> None:
    rig = homed_rig()
    assert rig.send(Command.START).success
    run_checking(
        rig, lambda: rig.state_machine.motion() is not None and rig.loop.axes.rotate.turns > 0.4
    )
    assert rig.send(Command.PAUSE).success
    rig.step(50)
    rec = latest(rig, "rotate")
    assert not rec.pn_status & (PnStatus.MOVING | PnStatus.SETTLED)  # held: not settled
    assert rotate_error(rig, rec) <= ROTATE_TOL_DEG
    assert rig.send(Command.RESUME).success
    run_checking(rig, lambda: rig.state is S.DONE)


def test_rotate_tracks_across_estop_and_resume() -> None:
    rig = homed_rig()
    assert rig.send(Command.START).success
    run_checking(rig, lambda: rig.loop.axes.rotate.turns > 1.3)
    rig.hal.press_estop()
    rig.step(30)
    rec = latest(rig, "rotate")
    assert rig.state is S.FAULT_ESTOP
    assert not rec.pn_status & (PnStatus.SETTLED | PnStatus.DRIVE_ENABLED | PnStatus.MOVING)
    assert rotate_error(rig, rec) <= ROTATE_TOL_DEG
    rig.hal.release_estop()
    rig.step()
    assert rig.send(Command.RESUME).success
    run_checking(rig, lambda: rig.state is S.DONE)
    assert latest(rig, "rotate").drive_fb == pytest.approx(3.0, abs=ROTATE_STEP_DEG / 360)


def test_ccw_revolutions_track_and_end_settled_at_the_arc() -> None:
    rig = homed_rig()
    session = Session(name="ccw", steps=[RotateStep(direction=Direction.CCW, revolutions=2)])
    assert rig.send(Command.START, session=session.model_dump()).success
    seen = run_checking(rig, lambda: rig.state is S.DONE)
    assert any(r.velocity_fb < 0 for r in seen)
    end = latest(rig, "rotate")
    assert end.pn_status & PnStatus.SETTLED
    assert end.drive_fb < -1.0  # turned CCW: negative turns


def test_a_hardware_fault_forgets_the_rotate_reference() -> None:
    rig = homed_rig()
    rig.hal.stall("rotate")
    assert rig.send(Command.START).success
    rig.run_to_state(S.FAULT_HW)
    rig.step()
    rec = latest(rig, "rotate")
    assert rec.pn_status & PnStatus.POSITION_UNKNOWN and not rec.position_known
    assert rig.loop.build_status(rig.clock()).rotate_deg is None


def test_axis_numbers_follow_the_seed_cells() -> None:
    rig = Rig()
    assert latest(rig, "rotate").axis_number == ROTATE_AXIS_NUMBER == 1
    assert latest(rig, "tilt").axis_number == TILT_AXIS_NUMBER == 2


# ------------------------------------------------------------------------ settled (bit 0)
def tilt_session(deg: float) -> dict[str, object]:
    return Session(name="tilt", steps=[TiltStep(degrees=deg)]).model_dump()


def test_tilt_command_is_the_target_not_the_feedback() -> None:
    rig = homed_rig()
    assert rig.send(Command.START, session=tilt_session(40.0)).success
    rig.step(20)
    rec = latest(rig, "tilt")
    assert rec.position_cmd == 40.0 and rec.position_fb < 10.0
    cal = known_calibration().tilt
    assert cal is not None
    assert rec.drive_cmd == cal.offset_counts + cal.gain_counts_per_deg * 40.0
    assert rec.drive_fb == float(rig.hal.world.sense().tilt_raw)
    rig.run_to_state(S.DONE)
    rig.step()
    assert latest(rig, "tilt").pn_status & PnStatus.SETTLED


def test_a_paused_move_is_not_settled() -> None:
    rig = homed_rig()
    assert rig.send(Command.START, session=tilt_session(40.0)).success
    rig.step(50)
    assert rig.send(Command.PAUSE).success
    rig.step(5)
    rec = latest(rig, "tilt")
    assert not rec.pn_status & PnStatus.MOVING
    assert not rec.pn_status & PnStatus.SETTLED


def test_a_move_stopped_short_of_its_target_is_not_settled() -> None:
    rig = homed_rig()
    assert rig.send(Command.START, session=tilt_session(40.0)).success
    rig.step(50)
    assert rig.send(Command.STOP).success
    rig.step(5)
    rec = latest(rig, "tilt")
    assert rig.state is S.DONE and not rec.pn_status & PnStatus.SETTLED
    rig.home()  # a new move that reaches its target settles again
    assert latest(rig, "tilt").pn_status & PnStatus.SETTLED


def test_a_fault_short_of_the_target_is_not_settled() -> None:
    rig = homed_rig()
    assert rig.send(Command.START, session=tilt_session(40.0)).success
    rig.step(50)
    rig.hal.stall("tilt")
    rig.run_to_state(S.FAULT_HW)
    rig.step()
    rec = latest(rig, "tilt")
    assert rec.pn_status & PnStatus.DRIVE_FAULT
    assert not rec.pn_status & PnStatus.SETTLED


def test_an_uncalibrated_tilt_is_unknown_not_settled_at_zero() -> None:
    rig = Rig()
    rec = latest(rig, "tilt")
    assert rec.pn_status & PnStatus.POSITION_UNKNOWN
    assert not rec.pn_status & PnStatus.SETTLED
    assert rec.drive_fb == float(rig.hal.world.sense().tilt_raw)  # raw counts need no calibration


def test_samples_at_rest_still_follow_the_world() -> None:
    """Idle cycles reuse the samples while nothing they depend on changes; a tilt moved by
    hand at rest is seen in the very next cycle, and both axes settle again after a move."""
    rig = Rig(calibration=known_calibration())
    rig.home()
    rig.step(50)  # long at rest
    before = rig.loop.axes.samples["tilt"].position_fb
    rig.hal.world.tilt_deg += 3.0  # pushed by hand: no relay, no command
    rig.step()
    moved = rig.loop.axes.samples["tilt"]
    assert abs(moved.position_fb - (before + 3.0)) < 0.05
    assert moved.velocity_fb > 0  # it moved between two cycles
    rig.step(5)
    still = rig.loop.axes.samples["tilt"]
    assert still.position_fb == moved.position_fb and still.velocity_fb == 0.0
    rig.hal.world.tilt_deg -= 3.0  # back on its home switch
    rig.step(2)
    assert abs(rig.loop.axes.samples["tilt"].position_fb - before) < 0.05
    assert rig.send(Command.START, session=Session(steps=[TiltStep(degrees=10.0)])).success
    rig.run_until(lambda: rig.state is not S.RUNNING)
    rig.step(50)
    tilt, rotate = rig.loop.axes.samples["tilt"], rig.loop.axes.samples["rotate"]
    assert tilt.velocity_fb == 0.0 and rotate.velocity_fb == 0.0
    assert tilt.status & PnStatus.SETTLED
    assert tilt.position_fb == rig.loop.devices.tilt.read_position_degrees()  # as read now


def test_a_calibration_entered_at_rest_republishes_the_tilt_record() -> None:
    """Issue 37: the idle tilt record kept the old position (FastData pFb 0.000 while the status
    said -0.1°) until the axis next moved; same bits, another position: published again."""
    rig = homed_rig()
    rig.step(200)  # long at rest: quiet cycles
    before = latest(rig, "tilt")
    cal = rig.state_machine.calibration.tilt
    assert cal is not None
    entered = CalibrationSet(
        transaction_id="c1",
        tilt=TiltCalibrationSet(offset_counts=cal.offset_counts + 6, gain_counts_per_deg=40.0),
    )
    rig.state_machine.enter_calibration(entered, rig.clock())
    rig.step()
    after = latest(rig, "tilt")
    status = rig.loop.published.status
    assert status is not None and status.tilt_deg is not None
    assert after.cycle > before.cycle
    assert after.position_fb == pytest.approx(before.position_fb - 6 / 40.0)
    assert round(after.position_fb, 2) == status.tilt_deg


def test_a_calibration_entered_at_rest_is_no_speed() -> None:
    """Issue 58, point 9: after `calibration set --tilt-offset 1300` on an idle machine the
    standing tilt was reported at about −321°/s until it moved (its position jumped by the new
    offset in one cycle). A calibration change resets the speed estimate."""
    rig = homed_rig()
    rig.step(50)
    cal = rig.state_machine.calibration.tilt
    assert cal is not None
    entered = CalibrationSet(
        transaction_id="c9",
        tilt=TiltCalibrationSet(offset_counts=cal.offset_counts + 30, gain_counts_per_deg=40.0),
    )
    rig.state_machine.enter_calibration(entered, rig.clock())
    for _ in range(3):
        rig.step()
        assert latest(rig, "tilt").velocity_fb == 0.0
