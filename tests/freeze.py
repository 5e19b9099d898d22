"""A daemon frozen the ways a real one freezes, under `machine supervise` as the README runs it
(no --zenoh-config: Zenoh's own 10 s lease), and what its ride's relays do meanwhile.

Shared by tests/reliability/test_output_guard.py and bench/freeze.py. The freezes:
- `SIGSTOP`: every thread of the process stops (a kernel that does not schedule it);
- `GIL`: the scan thread holds the GIL for ever (tests/fixtures/freeze/sitecustomize.py);
- `SYSCALL`: the scan thread blocks in a system call that never returns (the same hooks).
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from enum import StrEnum
from pathlib import Path

from bench.daemon import calibration_file
from ride_machine.rider.client import MachineTimeout, Rider
from ride_machine.schema.commands import Reply, Session, TiltStep
from ride_machine.schema.sim import SimWorldState
from ride_machine.schema.status import FaultCode, MachineState, Status
from ride_machine.service.core.storage.persist import CALIBRATION_FILE
from tests.fixtures.revpi import CONFIG_RSC, address
from tests.integration.support import Preparation, late_steps
from tests.procs import (
    REPO,
    Daemon,
    children_running,
    free_port,
    machine_cmd,
    stop_process,
    write_zenoh_config,
)

HOOKS = REPO / "tests" / "fixtures" / "freeze"
RELAYS = ("O_1", "O_2", "O_3", "O_4")
LIMIT_S = 0.1
"""The watchdog limit of the frozen daemons: the project's default (3 periods, at least 0.1 s)."""
PERIOD_S = 0.010
TILT_DPS = 15.0
ROTATE_DPS = 90.0

FREEZE_CONFIG = f"""\
# The project's defaults (real speeds, 10 ms period, the default watchdog limit), a rotate
# that starts just short of its home switch, and a status heartbeat of 0.2 s.
[loop]
period_s = {PERIOD_S}
watchdog_periods = 3
watchdog_min_s = {LIMIT_S}

[bus]
heartbeat_s = 0.2

[rider_loss]
timeout_s = 2.0

[hal.sim]
start_rotate_deg = 350.0
start_tilt_deg = 2.0
"""
PUMP_CONFIG = """
[hal.iomap]
chargePump = "O_5"   # the drives' power hangs on the charge pump's relay (0.1 s)
"""
"""Added unless a test asks for the ride without a charge pump (the old behaviour)."""


class Freeze(StrEnum):
    SIGSTOP = "sigstop"
    GIL = "gil"
    SYSCALL = "syscall"


SIGNALS = {
    Freeze.SIGSTOP: signal.SIGSTOP,
    Freeze.GIL: signal.SIGRTMIN + 1,  # the hooks' (tests/fixtures/freeze/sitecustomize.py)
    Freeze.SYSCALL: signal.SIGRTMIN + 2,
}


def freeze(pid: int, kind: Freeze) -> float:
    """Freeze `pid` now; the monotonic time just before the signal went."""
    t0 = time.monotonic()
    os.kill(pid, SIGNALS[kind])
    return t0


def hooked_env() -> dict[str, str]:
    """The environment of a supervisor whose daemon children take the freeze hooks."""
    path = os.pathsep.join(p for p in (str(HOOKS), os.environ.get("PYTHONPATH", "")) if p)
    return {**os.environ, "PYTHONPATH": path, "MACHINE_TEST_FREEZE": "1", "PYTHONUNBUFFERED": "1"}


def start_supervised(tmp: Path, *extra: str, pump: bool = True) -> Daemon:
    """`machine supervise --sim` with no Zenoh config (the README's way), calibrated, not yet
    waited for; its Riders use a test Zenoh config of their own. `pump=False`: the ride has no
    charge pump (the drives' power does not depend on the controller)."""
    data_dir = tmp / "data-m1"
    data_dir.mkdir(parents=True, exist_ok=True)
    (data_dir / CALIBRATION_FILE).write_bytes(calibration_file())
    config = tmp / "machine-freeze.toml"
    config.write_text(FREEZE_CONFIG + (PUMP_CONFIG if pump else ""))
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    log_path = tmp / "supervise.log"
    cmd = machine_cmd(
        "supervise",
        "--sim",
        "--listen",
        endpoint,
        "--data-dir",
        str(data_dir),
        "--config",
        str(config),
        "--backoff",
        "0.2",
        "--backoff-max",
        "0.5",
        *extra,
    )
    with log_path.open("w") as log:
        proc = subprocess.Popen(
            cmd, stdout=log, stderr=subprocess.STDOUT, text=True, cwd=REPO, env=hooked_env()
        )
    return Daemon(proc, endpoint, "m1", data_dir, write_zenoh_config(tmp), log_path)


def image_relays(data_dir: Path) -> dict[str, bool]:
    """The relay bits in the supervisor's process-image file, read without revpimodio2."""
    image = (data_dir / "supervisor" / "procimg").read_bytes()
    out = {}
    for name in RELAYS:
        byte, bit = address(name, CONFIG_RSC)
        assert bit is not None
        out[name] = bool(image[byte] >> bit & 1)
    return out


def relays_off_at(data_dir: Path, timeout: float) -> float | None:
    """The monotonic time the image first shows every relay off, looked at every 0.2 ms; None
    if they are still on after `timeout` s."""
    deadline = time.monotonic() + timeout
    while True:
        now = time.monotonic()
        if not any(image_relays(data_dir).values()):
            return now
        if now > deadline:
            return None
        time.sleep(0.0002)


def child_of(supervisor: Daemon, timeout: float = 20.0) -> int:
    """The pid of the supervisor's daemon child, once there is exactly one."""
    deadline = time.monotonic() + timeout
    while True:
        out = children_running(supervisor.proc.pid, "ride_machine.service.cli")
        if len(out) == 1:
            return out[0]
        if time.monotonic() > deadline:
            raise TimeoutError(f"expected one daemon child of the supervisor, found {out}")
        time.sleep(0.05)


@dataclass(frozen=True)
class Outcome:
    """One freeze: how long until the relays were off, and how far the tilt went meanwhile."""

    kind: Freeze
    off_s: float | None
    overrun_deg: float | None


def stop(supervisor: Daemon) -> int:
    return stop_process(supervisor.proc)


def ride_and_freeze(supervisor: Daemon, rider: Rider, kind: Freeze) -> Outcome:
    """Home, drive the tilt towards 45°, freeze the daemon 5° into the move; when the relays
    are off in the image, how long that took and how far the tilt travelled past the freeze.
    Returns once the supervisor has a new daemon up (not home)."""
    before = child_of(supervisor)
    ready(rider)
    moving: list[tuple[SimWorldState, float]] = []

    def going(_: Reply) -> Status:
        """The tilt 5° into its move (the world then, and when it was read), or the fault
        that ended the move first: a late world's or a stall's (`Preparation.excuse`), as the
        freezes, not this (loaded) host's own stalls, are the subject here."""
        world = tilt_moving(rider)
        if world is not None:
            moving.append((world, time.monotonic()))
        return rider.status()

    ride_the_tilt(rider, going)
    world, seen_at = moving[-1]
    t0 = freeze(before, kind)
    off = relays_off_at(supervisor.data_dir, timeout=15.0)
    after = rider.sim("world")
    overrun = after.tilt_deg - (world.tilt_deg + TILT_DPS * (t0 - seen_at))
    replaced(supervisor, rider, before)
    return Outcome(kind, None if off is None else off - t0, overrun)


def ride_the_tilt(rider: Rider, going: Callable[[Reply], Status]) -> None:
    """Home, then a session towards 45°, through `Preparation`; `going` waits until the tilt
    is on its way. The tilt's calibration is the file's (not measured here): a tilt fault is
    excused only by the world's lateness during this call."""

    def start() -> Reply:
        reply = rider.start(Session(name="freeze", steps=[TiltStep(degrees=45.0)]))
        assert reply.success, reply
        return reply

    Preparation(rider, tilt_late=late_steps(rider)).ride(start, going)


@contextlib.contextmanager
def supervised(
    tmp: Path, *, pump: bool = True, timeout: float = 3.0, ready_s: float | None = None
) -> Iterator[tuple[Daemon, Rider]]:
    """`start_supervised` in `tmp` and a Rider of the test's own (its calls bounded by
    `timeout`; `ready_s`: first wait that long for a daemon), stopped after the block."""
    tmp.mkdir(parents=True, exist_ok=True)
    supervisor = start_supervised(tmp, pump=pump)
    try:
        with supervisor.rider(timeout=timeout, supervise=False) as rider:
            if ready_s is not None:
                ready(rider, timeout=ready_s)
            yield supervisor, rider
    finally:
        stop(supervisor)


def tilt_moving(rider: Rider, timeout: float = 30.0) -> SimWorldState | None:
    """The world once the tilt is driven 5° into its move; None if the move ended first."""
    deadline = time.monotonic() + timeout
    while (world := rider.sim("world")).tilt_deg < 5.0 or not any(world.relays.values()):
        if rider.status().state is MachineState.FAULT_HW:
            return None
        assert time.monotonic() < deadline, f"the tilt never moved: {world}"
        time.sleep(0.01)
    return world


def ready(rider: Rider, timeout: float = 30.0) -> Status:
    """The machine's status once a daemon is up and answering (not the supervisor's stand-in)."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            status = rider.status()
            if status.fault is None or status.fault.code is not FaultCode.DAEMON_DIED:
                return status
        except MachineTimeout:
            pass
        if time.monotonic() > deadline:
            raise TimeoutError("no daemon answered")
        time.sleep(0.05)


def replaced(supervisor: Daemon, rider: Rider, before: int, timeout: float = 30.0) -> Status:
    """Once the frozen daemon `before` is gone and a new one answers: its first status."""
    deadline = time.monotonic() + timeout
    while True:
        with contextlib.suppress(TimeoutError):
            if child_of(supervisor, timeout=0.5) != before:
                break
        if time.monotonic() > deadline:
            raise TimeoutError(f"daemon {before} was not replaced:\n{supervisor.log()[-3000:]}")
        time.sleep(0.05)
    return ready(rider, timeout)
