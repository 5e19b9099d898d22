"""Issue 37's reproductions through a real daemon, the real `rider` CLI and real Zenoh: a seat
found below its home switch, a host that stalls scans, a calibration typed in by hand with the
wrong gain, and what FastData and the event history say after `calibration set`.

The tilt runs at the project's default speed (15°/s, one 10 ms scan = 0.15°), so its
tolerances are the documented ones (docs/homing.md); the rotate is the fast one, to keep the
tests short.
"""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from ride_machine.rider.client import Rider
from ride_machine.rider.fastdata import FastDataClient
from ride_machine.schema.axes import TILT_AXIS_NUMBER
from ride_machine.schema.commands import RotateStep, Session, TiltStep
from ride_machine.schema.events import CalibrationEvent
from ride_machine.schema.status import FaultCode, MachineState, Status
from tests.integration.support import FAST_ROTATE, SPOILED, settle
from tests.procs import Daemon, free_port, running_daemon
from tests.rig import WIDE_SCALE

pytestmark = pytest.mark.integration

HOMING_CONFIG = """\
[loop]
watchdog_periods = 100   # the tests stall scans on purpose; a loaded CI host does too

[rider_loss]
timeout_s = 1.0

[tilt]
calibration_stroke_s = 1.0
{tilt}

{fast_rotate}
[hal.sim]
rotate_speed_dps = 720.0
home_arc_deg = 30.0
start_tilt_deg = {start_tilt}
tilt_home_hysteresis_deg = 0.5
{extra}
"""
OFFSET_TOL_DEG = 0.25
POSITION_TOL_DEG = 0.5
GAIN = 40.0
"""The simulator's analog gain (counts/°)."""
CLI_TIMEOUT_S = 90.0


UNCOMMISSIONED = "\n".join(f"{key} = {value!r}" for key, value in WIDE_SCALE.items())
"""`[tilt]` lines of a sensor scale as wide as the config allows: the witnesses alone judge."""


def config(tmp: Path, start_tilt: float = 12.0, extra: str = "", tilt: str = "") -> list[str]:
    path = tmp / "machine-homing.toml"
    text = HOMING_CONFIG.format(
        fast_rotate=FAST_ROTATE, start_tilt=start_tilt, extra=extra, tilt=tilt
    )
    path.write_text(text)
    return ["--config", str(path)]


def calibrate_tilt(daemon: Daemon) -> str | None:
    """`rider calibrate tilt --wait`: None when DONE, else the fault code it was refused with."""
    done = daemon.cli("calibrate", "tilt", "--wait", timeout=CLI_TIMEOUT_S)
    if done.returncode == 0:
        return None
    assert any(code in done.stderr for code in SPOILED), done.stdout + done.stderr
    return done.stderr


def offset_error_deg(r: Rider) -> float:
    """The measured tilt offset against the simulator's truth, in degrees."""
    tilt = r.calibration().tilt
    assert tilt is not None
    zero = r.sim("world").tilt_zero_counts
    assert zero is not None
    return abs(tilt.offset_counts - zero) / GAIN


def positions_error(r: Rider, status: Status) -> tuple[float, float]:
    """(tilt, rotate) as the status reports them against the simulator's truth, in degrees."""
    world = r.sim("world")
    assert status.tilt_deg is not None and status.rotate_deg is not None, status
    rotate = abs((status.rotate_deg - world.rotate_deg + 180.0) % 360.0 - 180.0)
    return abs(status.tilt_deg - world.tilt_deg), rotate


def test_a_seat_below_its_switch_and_a_stalling_host_measure_the_true_zero(tmp_path: Path) -> None:
    """Issue 37, points 1-3: calibration took the offset wherever it found the switch closed
    (1000 counts for 1200 from a -5° rest), and where the scan happened to run on a loaded
    host. Now from -5°, and again from 20° with 1 scan in 10 stalled up to 50 ms, the offset is
    the truth's within ±0.25° (or refused, never DONE), and a session ends where it says."""
    with (
        running_daemon(tmp_path, extra=config(tmp_path, -5.0, "tilt_noise_counts = 2.0")) as daemon,
        daemon.rider(timeout=5.0) as r,
    ):
        assert r.sim("world").tilt_home_closed  # resting on the switch, below its edge
        assert calibrate_tilt(daemon) is None
        assert offset_error_deg(r) <= OFFSET_TOL_DEG

        r.sim("stalls", probability=0.1, max_s=0.05)
        r.sim("place", tilt_deg=30.0)
        if calibrate_tilt(daemon) is None:
            assert offset_error_deg(r) <= OFFSET_TOL_DEG
        else:
            assert r.status().state is MachineState.FAULT_HW
        assert r.sim("world").stalled_s > 0.0
        r.sim("stalls", probability=0.0)
        if not r.status().calibrated.tilt or r.status().fault is not None:
            assert calibrate_tilt(daemon) is None

        assert daemon.cli("calibrate", "rotate", "--wait").returncode == 0
        homed = settle(r, r.home())
        assert homed.state is MachineState.IDLE, homed
        tilt_err, _ = positions_error(r, homed)
        assert tilt_err <= POSITION_TOL_DEG
        session = Session(name="short", steps=[TiltStep(degrees=20.0), RotateStep()])
        ended = settle(r, r.start(session))
        assert ended.state is MachineState.DONE, ended
        tilt_err, rotate_err = positions_error(r, ended)
        assert tilt_err <= POSITION_TOL_DEG
        assert rotate_err <= 8.0  # the fast rotate's latch tolerance


def home_faults_within(daemon: Daemon, r: Rider, travel_deg: float) -> FaultCode:
    """`rider home --wait` ends in a fault after less than `travel_deg` of true tilt travel."""
    before = r.sim("world").tilt_deg
    done = daemon.cli("home", "--wait", timeout=CLI_TIMEOUT_S)
    assert done.returncode == 1, done.stdout + done.stderr
    moved = abs(r.sim("world").tilt_deg - before)
    assert moved < travel_deg, (moved, done.stderr)
    fault = r.status().fault
    assert fault is not None and fault.axis == "tilt", fault
    return fault.code


def test_a_tilt_gain_typo_stops_within_a_few_degrees_not_at_the_end_stop(tmp_path: Path) -> None:
    """Issue 37, point 4: `calibration set --tilt-gain 400` (40 is right; 400 is in range) drove
    the tilt to its end stop at 95° while the status said 9.5°. Values typed in are not
    trusted until a Home has checked them with a measured move: Start is refused until then,
    and the Home stops within one speed window (0.2 s, 3° at 15°/s), from above the switch
    and from on it."""
    # A machine whose sensor scale was never narrowed (the default's refuses 400 at entry).
    with running_daemon(tmp_path, extra=config(tmp_path, tilt=UNCOMMISSIONED)) as daemon:
        typo = ["--tilt-offset", "1194", "--tilt-gain", "400"]
        rotate = ["--rotate-revolution-s", "0.5", "--rotate-home-arc", "30"]
        entered = daemon.cli("calibration", "set", *typo, *rotate)
        assert entered.returncode == 0, entered.stderr
        start = daemon.cli("start", "--wait")
        assert start.returncode == 1 and "NOT_HOME" in start.stderr, start.stderr
        with daemon.rider(timeout=5.0) as r:
            assert home_faults_within(daemon, r, 5.0) is FaultCode.TILT_SPEED_IMPLAUSIBLE
            r.sim("place", tilt_deg=-0.1)  # resting home: Home backs off up first
            assert home_faults_within(daemon, r, 5.0) is FaultCode.TILT_SPEED_IMPLAUSIBLE
            assert r.sim("world").tilt_deg < 10.0


@pytest.mark.hazard("H21")
def test_a_gain_typed_30_percent_wrong_is_never_done_at_the_wrong_angle(tmp_path: Path) -> None:
    """Issue 53, point 1: `calibration set --tilt-offset 1197 --tilt-gain 52` (40 is measured),
    `home --wait`, `start --wait` ended DONE "at 44.6°" with the simulated tilt at 57.9°, and a
    one-step session to 60° DONE at "59.6°" with the tilt at 77.3°, past `tilt.max_deg`: 23 %
    slow is inside the speed window's ±30 %. Now the Home verifies the entered values (a zero, a
    stroke, the zero again) and stops on the speed witness's code; nothing rides on them."""
    extra = config(tmp_path, tilt=UNCOMMISSIONED)  # the scale's refusal: tests/…/test_scale.py
    with running_daemon(tmp_path, extra=extra) as daemon, daemon.rider() as r:
        rotate = ["--rotate-revolution-s", "0.5", "--rotate-home-arc", "30"]
        typed = ["--tilt-offset", "1197", "--tilt-gain", "52", *rotate]
        assert daemon.cli("calibration", "set", *typed).returncode == 0
        record = r.calibration()
        deadline = time.monotonic() + 2.0  # published with the cycle after the write (bounded)
        while record.tilt is None and time.monotonic() < deadline:
            time.sleep(0.01)
            record = r.calibration()
        assert record.tilt is not None and record.tilt.verified is False
        home = daemon.cli("home", "--wait", timeout=CLI_TIMEOUT_S)
        assert home.returncode == 1, home.stdout + home.stderr
        status = r.status()
        assert status.state is MachineState.FAULT_HW and status.fault is not None, status
        assert status.fault.code is FaultCode.TILT_GAIN_MISMATCH, status.fault
        assert "52" in status.fault.message and "counts/°" in status.fault.message
        sixty = tmp_path / "sixty.json"
        sixty.write_text('{"name": "sixty", "steps": [{"kind": "tilt", "degrees": 60}]}')
        for session in ([], ["--session", str(sixty)]):
            start = daemon.cli("start", "--wait", *session, timeout=CLI_TIMEOUT_S)
            assert start.returncode == 1 and "NOT_HOME" in start.stderr, start.stderr
        world = r.sim("world")
        assert world.tilt_deg <= 61.0 and not any(world.relays.values()), world
        # The right values, typed: verified by the same Home, and the ride goes where it says.
        right = ["--tilt-offset", "1200", "--tilt-gain", "40"]
        assert daemon.cli("calibration", "set", *right).returncode == 0
        assert daemon.cli("home", "--wait", timeout=CLI_TIMEOUT_S).returncode == 0
        record = r.calibration()
        assert record.tilt is not None and record.tilt.verified is True
        ride = daemon.cli("start", "--wait", "--session", str(sixty), timeout=CLI_TIMEOUT_S)
        assert ride.returncode == 0, ride.stdout + ride.stderr
        ended = r.status()
        tilt_err, _ = positions_error(r, ended)
        assert ended.state is MachineState.DONE and tilt_err <= POSITION_TOL_DEG, ended


def test_calibration_set_republishes_the_idle_tilt_and_the_history_tells_a_failed_save(
    tmp_path: Path,
) -> None:
    """Issue 37, point 5: after `calibration set` FastData's idle tilt record kept its old pFb,
    and the history recorded a calibration whose save failed as persisted=True. Here the
    first save fails for real (calibration.json is a directory: a botched deploy) and moves
    it aside, so the second one is saved."""
    (tmp_path / "data-m1" / "calibration.json").mkdir(parents=True)
    udp = free_port()
    fastdata = f'[fastdata]\nenabled = true\nhost = "127.0.0.1"\nport = {udp}\n'
    extra = config(tmp_path)
    Path(extra[1]).write_text(Path(extra[1]).read_text() + fastdata)
    rotate = ["--rotate-revolution-s", "0.5", "--rotate-home-arc", "30"]
    with (
        running_daemon(tmp_path, extra=extra) as daemon,
        daemon.rider(timeout=5.0) as r,
        FastDataClient("127.0.0.1", udp, timeout=2.0) as fast,
    ):
        first = daemon.cli(
            "calibration", "set", "--tilt-offset", "1194", "--tilt-gain", "40", *rotate
        )
        assert first.returncode == 1 and "STORAGE_FAILED" in first.stderr, first.stderr
        second = daemon.cli("calibration", "set", "--tilt-offset", "1180", "--tilt-gain", "40")
        assert second.returncode == 0, second.stderr
        # The reply comes once the calibration is saved; the cycle that applied it publishes
        # the tilt (a loaded host may answer the status read from the cycle before).
        status = r.status()
        deadline = time.monotonic() + 5.0
        while status.tilt_deg is None or abs(status.tilt_deg - (12.0 + 20 / GAIN)) > 0.1:
            assert time.monotonic() < deadline, f"the idle tilt was not republished: {status}"
            status = r.status()
        (tilt,) = fast.query([TILT_AXIS_NUMBER]).axes
        assert round(tilt.pFb, 2) == status.tilt_deg
        # The history records a calibration once its write has ended, at the first cycle after
        # (service/core/history/events.py): a read right after the reply may come before it.
        deadline = time.monotonic() + 5.0
        while len(tilts := _tilt_calibrations(r)) < 2 and time.monotonic() < deadline:
            pass
        assert [d.persisted for d in tilts] == [False, True], tilts


def _tilt_calibrations(r: Rider) -> list[CalibrationEvent]:
    events = [e.details for e in r.events(kinds=("calibration",))]
    return [d for d in events if isinstance(d, CalibrationEvent) and d.axis == "tilt"]
