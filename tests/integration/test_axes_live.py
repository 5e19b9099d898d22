"""Axis positions, FastData bits and user registers through a real daemon: Zenoh and UDP clients.

One daemon on the fast simulator with FastData on; then a restart on the same data directory.
"""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from ride_machine.rider.client import Rider
from ride_machine.rider.fastdata import FastDataClient
from ride_machine.schema.axes import ROTATE_AXIS_NUMBER, TILT_AXIS_NUMBER, AxisRecord, PnStatus
from ride_machine.schema.commands import Direction, RotateStep, Session, TiltStep
from ride_machine.schema.fastdata import USER_REGISTER_LENGTH, FastAxisData
from ride_machine.schema.status import MachineState
from tests.integration.support import FAST_CONFIG, STEP_TIMEOUT_S, prepare, settle
from tests.procs import Daemon, free_port, running_daemon

SESSION = Session(
    name="live",
    steps=[TiltStep(degrees=20.0), RotateStep(direction=Direction.CW, revolutions=4)],
)


def config(tmp: Path, udp_port: int) -> list[str]:
    path = tmp / "machine-axes.toml"
    text = FAST_CONFIG.format(heartbeat_s=0.2)
    path.write_text(f'{text}\n[fastdata]\nenabled = true\nhost = "127.0.0.1"\nport = {udp_port}\n')
    return ["--config", str(path)]


def rotate_fast(client: FastDataClient) -> FastAxisData:
    (rec,) = client.query([ROTATE_AXIS_NUMBER]).axes
    return rec


def rotate_zenoh(rider: Rider) -> AxisRecord:
    return next(a for a in rider.axes() if a.axis == "rotate")


def set_register(daemon: Daemon, *args: str) -> None:
    done = daemon.run_rider("fastdata", *args)
    assert done.returncode == 0, done.stderr


def sample_moving(fast: FastDataClient) -> list[FastAxisData]:
    """The rotate axis's records while it moves. Sampled until past 1.5 turns with 40 samples,
    or until the 4 turns (about 2 s) are over: the 1.5 turns alone (0.75 s) hold 40 samples
    only while a poll takes under 19 ms, which a loaded host does not promise."""
    moving: list[FastAxisData] = []
    deadline = time.monotonic() + STEP_TIMEOUT_S
    while time.monotonic() < deadline and not (len(moving) >= 40 and moving[-1].cFb > 1.5):
        rec = rotate_fast(fast)
        if rec.pnStatus & PnStatus.MOVING:
            moving.append(rec)
        elif moving:
            break  # the rotation is over
        time.sleep(0.01)  # polls a UDP server: there is no event to wait on
    return moving


def test_positions_bits_and_registers_through_zenoh_and_udp(tmp_path: Path) -> None:
    udp = free_port()
    extra = config(tmp_path, udp)
    with (
        running_daemon(tmp_path, extra=extra) as daemon,
        daemon.rider(timeout=5.0) as rider,
        FastDataClient("127.0.0.1", udp, timeout=2.0) as fast,
    ):
        # Start-up: never homed, the rotate position is unknown, and every client is told so.
        rec = rotate_fast(fast)
        assert rec.axisnumber == ROTATE_AXIS_NUMBER
        assert rec.pnStatus & PnStatus.POSITION_UNKNOWN and not rec.pnStatus & PnStatus.SETTLED
        assert not rotate_zenoh(rider).position_known
        assert rider.status().rotate_deg is None
        prepare(rider)  # calibrate, then Home
        rec = rotate_fast(fast)
        assert not rec.pnStatus & PnStatus.POSITION_UNKNOWN and rec.pnStatus & PnStatus.SETTLED
        assert rider.status().rotate_deg is not None

        reply = rider.start(SESSION)
        moving = sample_moving(fast)
        zen = rotate_zenoh(rider)
        end = settle(rider, reply)
        assert end.state is MachineState.DONE, end
        assert len(moving) >= 40
        assert all(not r.pnStatus & (PnStatus.POSITION_UNKNOWN | PnStatus.SETTLED) for r in moving)
        assert all(r.vCmd > 0 for r in moving)
        # vFb is the speed over the interval just past: 0 only in the cycle the relay closed.
        assert sum(r.vFb > 0 for r in moving) >= len(moving) - 1
        assert max(r.pFb for r in moving) - min(r.pFb for r in moving) > 90  # not stuck at 0
        assert moving[-1].cFb > 1.5  # turns since home grow past one revolution
        assert zen.position_known
        rec = rotate_fast(fast)
        # Four turns, latched midway between the scans either side of the last edge: within
        # the fast rotate's latch tolerance (8°) of it (docs/homing.md).
        assert rec.pnStatus & PnStatus.SETTLED and rec.cCmd == pytest.approx(4.0, abs=1e-9)
        assert abs(rec.cFb - 4.0) <= 8.0 / 360
        (tilt,) = fast.query([TILT_AXIS_NUMBER]).axes
        assert tilt.pCmd == 20.0 and tilt.cCmd != tilt.pCmd  # target in degrees and in counts

        # User registers: set by the operator, carried by every reply; one of them persisted.
        set_register(daemon, "set-int", "2", "42", "--persist")
        rider.set_param("fastdata.double.7", 2.5)
        got = fast.query([ROTATE_AXIS_NUMBER])
        assert len(got.ints) == len(got.doubles) == USER_REGISTER_LENGTH
        assert got.ints[2] == 42 and got.doubles[7] == 2.5

    # A restart: the persisted register is back, the rotate position is unknown until Home.
    with (
        running_daemon(tmp_path, extra=extra) as daemon,
        daemon.rider(timeout=5.0) as rider,
        FastDataClient("127.0.0.1", udp, timeout=2.0) as fast,
    ):
        got = fast.query([ROTATE_AXIS_NUMBER])
        assert got.ints[2] == 42 and got.doubles[7] == 0.0
        assert got.axes[0].pnStatus & PnStatus.POSITION_UNKNOWN
        assert rider.status().rotate_deg is None
        prepare(rider)
        assert not rotate_fast(fast).pnStatus & PnStatus.POSITION_UNKNOWN
