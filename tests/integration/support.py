"""Shared by the integration tests: a fast simulator config and waits that end on events.

The fast config speeds the simulated mechanics up (one revolution in 0.5 s, tilt 90°/s) so a
whole calibrate → home → session run takes a few seconds, and loosens the loop watchdog so a
loaded CI host does not trip it in the middle of a test.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, TypeVar

import pytest
import zenoh

from ride_machine.rider.client import Rider
from ride_machine.schema.codec import Format
from ride_machine.schema.commands import REST_STATES, Reply
from ride_machine.schema.status import FAULT_STATES, FaultCode, MachineState, Status
from tests.procs import Daemon, running_daemon

FAST_ROTATE = """\
[rotate]
nominal_speed_dps = 720.0
home_arc_deg = 30.0
revolution_timeout_s = 2.0
backoff_timeout_s = 1.0
# One 10 ms scan is 7.2° here: the latch tolerances follow the speed (docs/homing.md), and a
# revolution of 0.5 s may take half again as long on a host that stalls the scan.
latch_tolerance_deg = 8.0
repeat_tolerance_deg = 16.0
runup_s = 0.02
revolution_tolerance = 0.5
settle_window_deg = 8.0  # settled within the latch's reach
"""
"""The fast rotate (one revolution in 0.5 s), for a config whose tilt is another's."""

FAST_CONFIG = (
    FAST_ROTATE
    + """
[tilt]
nominal_speed_dps = 90.0
home_timeout_s = 3.0
move_timeout_margin_s = 1.0
calibration_stroke_s = 0.4
follow_window_s = 0.3
# One 10 ms scan is 0.9° here.
latch_tolerance_deg = 1.5
repeat_tolerance_deg = 3.0
home_tolerance_deg = 3.0
runup_s = 0.12
speed_window_s = 0.1
# The home switch's raw value ± 3° (a latch here may be 1.5° off): 1200 ± 120 counts. A
# 0.4 s stroke at 90°/s on a loaded host measures the gain within ~10 % (43.7 seen beside two
# CPU-bound processes), not the 5 % of a 2 s stroke at 15°/s: a band of ± 15 % here.
zero_min_counts = 1080.0
zero_max_counts = 1320.0
gain_min_counts_per_deg = 34.0
gain_max_counts_per_deg = 46.0
# The drive's speed witness judges strokes of a few tenths of a second here: 0.3° at 60° (0.5 %)
# is finer than they measure beside a loaded suite (-2.6 % seen, a compose stack in CI).
gain_tolerance_deg = 2.0

[loop]
# A shared 2-core host stalls the scan thread for tens of ms now and then; 3 periods (the
# default) would trip the watchdog in the middle of a test that is not about the watchdog.
watchdog_periods = 100

[rider_loss]
# The deadman default (0.5 s) pauses a ride when a Rider's heartbeat thread is starved that
# long; on a loaded shared CI host that happens to tests that are not about it.
timeout_s = 1.0

[bus]
heartbeat_s = {heartbeat_s}
diag_period_s = 0.5

[hal.sim]
rotate_speed_dps = 720.0
home_arc_deg = 30.0
tilt_speed_dps = 90.0
"""
)

SETTLED = REST_STATES | FAULT_STATES
"""States in which a motion command has ended, well or not."""

STEP_TIMEOUT_S = 20.0
"""Bound for one motion (calibration, homing, a session): seconds at the fast config."""
SPOILED = frozenset({FaultCode.CALIBRATION_NOT_REPEATABLE, FaultCode.HOME_EDGE_UNCERTAIN})
"""The refusals of a measurement two latches disagree on: the machine's right answer when a
stall of a loaded host (the scan, or the supervised simulator's world) spoiled the timing; at
the fast config's 720°/s its 16° are 22 ms. Tests not about homing calibrate again on these."""


def write_fast_config(directory: Path, heartbeat_s: float = 0.2) -> Path:
    """The fast config; status is republished every `heartbeat_s` even when nothing changes."""
    path = directory / "machine-fast.toml"
    path.write_text(FAST_CONFIG.format(heartbeat_s=heartbeat_s))
    return path


def fast_args(directory: Path, *more: str, heartbeat_s: float = 0.2) -> list[str]:
    """`machine run` arguments for the fast simulator."""
    return ["--config", str(write_fast_config(directory, heartbeat_s)), *more]


@contextlib.contextmanager
def fast_daemon(
    tmp: Path, machine_id: str = "m1", *, heartbeat_s: float = 0.2, **kwargs: object
) -> Iterator[Daemon]:
    extra = fast_args(tmp, heartbeat_s=heartbeat_s)
    with running_daemon(tmp, machine_id, extra=extra, **kwargs) as daemon:
        yield daemon


def module_machine(name: str) -> Any:
    """A module-scoped `machine` fixture: one fast daemon shared by the tests of a module.

    Use as `machine = module_machine("session")` at module level.
    """

    @pytest.fixture(scope="module")
    def machine(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Daemon]:
        with fast_daemon(tmp_path_factory.mktemp(name)) as daemon:
            yield daemon

    return machine


def one_reply(session: zenoh.Session, selector: str, timeout: float = 10.0) -> zenoh.Sample:
    """The one ok reply to `selector`, asked again while none comes (a daemon not yet seen by
    a fresh session), within `timeout`."""
    deadline = time.monotonic() + timeout
    while True:
        replies = [r.ok for r in session.get(selector, timeout=5.0) if r.ok is not None]
        if replies or time.monotonic() > deadline:
            break
    [sample] = replies
    return sample


def raw_get(
    rider: Rider, key: str, payload: bytes | str, fmt: Format, timeout: float
) -> list[zenoh.Reply]:
    """Every reply to one query on the machine's `key` outside the typed client (the payload
    as given, its encoding `fmt`), as any Zenoh client could send it."""
    return list(
        rider.session.get(
            f"{rider.base}/{key}", payload=payload, encoding=fmt.value, timeout=timeout
        )
    )


def settle(rider: Rider, reply: Reply, timeout: float = STEP_TIMEOUT_S) -> Status:
    """Wait until the motion `reply` started has ended (a rest or fault state)."""
    return rider.wait_for(SETTLED, timeout, after=reply.timecode)


TILT_LATE_WORLD = frozenset(
    {FaultCode.TILT_NOT_FOLLOWING, FaultCode.TILT_SPEED_IMPLAUSIBLE, FaultCode.TILT_GAIN_MISMATCH}
)
"""The tilt's faults when its sensor stood still: the supervised simulator's world thread (not
the embedded one, which the scan steps), late on a loaded host, left the analog unchanged, and
the daemon rightly stopped the tilt. A tilt calibration measured meanwhile may carry a spoiled
gain that a later check finds too fast, or a stroke's speed witness too slow. Tests not about
it calibrate the tilt again, but only when the world itself counted a late step
(`SimWorldState.late_steps`) since that calibration began."""


class HostStalled(AssertionError):
    """A motion ended in a fault that the machine itself put down to its own scan stalling
    (`scan_stalled`): a test not about stalls rides its scenario again (`again_after_stall`)."""


def scan_stalled(status: Status) -> bool:
    """Whether `status` is a fault the machine measured as its own scan's stall: the watchdog
    tripped (no cycle for the test configs' 1 s with a relay on: a shared CI host once froze
    the daemon that long mid-ride, and the machine rightly went FAULT_HW), or a revolution
    overdue across a stall as long as the home switch stays closed."""
    fault = status.fault
    if status.state is not MachineState.FAULT_HW or fault is None:
        return False
    if fault.code is FaultCode.WATCHDOG:
        return True
    return fault.code is FaultCode.ROTATE_HOME_TIMEOUT and "the scan stalled" in fault.message


def not_stalled(status: Status) -> Status:
    """`status`, unless the machine says its scan stalled (`HostStalled`)."""
    if scan_stalled(status):
        raise HostStalled(f"the machine's own scan stalled: {status.fault}")
    return status


def spoiled(status: Status) -> bool:
    """Whether `status` is the machine's refusal of a measurement two latches disagree on
    (`SPOILED`), as a stall makes them."""
    fault = status.fault
    return status.state in FAULT_STATES and fault is not None and fault.code in SPOILED


def not_spoiled(status: Status) -> Status:
    """`status`, unless the machine says its scan stalled or refused a measurement as spoiled
    (`spoiled`; run 92, beside three burners: a rotate calibration's edges timed 0.500 s and
    0.564 s apart) (`HostStalled`)."""
    if spoiled(status):
        raise HostStalled(f"a measurement the machine refused as spoiled: {status.fault}")
    return not_stalled(status)


T = TypeVar("T")


def again_after_stall(scenario: Callable[[], T], tries: int = 3) -> T:
    """`scenario()`, run again (up to `tries` in all) when it met a fault the machine put down
    to its own scan stalling (`HostStalled`); any other failure fails at once."""
    for attempt in range(1, tries + 1):
        try:
            return scenario()
        except HostStalled:
            if attempt == tries:
                raise
    raise AssertionError("no tries")


def late_steps(rider: Rider) -> int:
    """The steps the simulated world came late so far (0 for the embedded one: never late)."""
    return rider.sim("world").late_steps or 0


class Preparation:
    """Brings a machine to IDLE, calibrated and homed, through the faults a loaded host causes
    (and no other): a refusal a stall spoiled (`SPOILED`) is measured again; a tilt fault while
    the simulated world was late (`TILT_LATE_WORLD`) calibrates the tilt again; a rotate whose
    home edge went unseen (`ROTATE_HOME_TIMEOUT`) homes again, when the daemon says its scan
    stalled as long as the switch stays closed (0.042 s at the fast config's 720°/s: a stall the
    embedded world waits out, the supervised one does not) or the world was late meanwhile; a
    watchdog trip (`scan_stalled`) homes again."""

    def __init__(self, rider: Rider, tilt_late: int = 0) -> None:
        self.rider = rider
        self._tilt_late = tilt_late
        """The world's late steps before the tilt's calibration in use began (when known: a
        calibration from a file, not measured here, began with the caller's count)."""
        self._redo_tilt = False
        self._moving_late = 0
        """The world's late steps before the last Home or Start this began."""

    def prepare(self, tries: int = 4) -> Status:
        """Calibrate what is not calibrated, then home; the machine ends IDLE."""
        for _ in range(tries):
            status = self._attempt()
            if status.state is MachineState.IDLE:
                return status
            self.excuse(status)
        raise AssertionError(f"{tries} tries in a row met a fault the loaded host caused")

    def _attempt(self) -> Status:
        rider = self.rider
        status = rider.status()
        # Each step from whatever state the last attempt left (a fault): the machine takes
        # a calibration or a Home from there.
        if self._redo_tilt or not status.calibrated.tilt:
            self._tilt_late, self._redo_tilt = late_steps(rider), False
            status = settle(rider, rider.calibrate_tilt())
            if status.state in FAULT_STATES:
                return status
        if not status.calibrated.rotate:
            status = settle(rider, rider.calibrate_rotate())
            if status.state in FAULT_STATES:
                return status
        self._moving_late = late_steps(rider)
        return settle(rider, rider.home())

    def ride(
        self,
        start: Callable[[], Reply],
        going: Callable[[Reply], Status],
        started: Reply | None = None,
        tries: int = 3,
    ) -> tuple[Reply, Status]:
        """Prepare, `start` a session and wait until it is `going` (a status, or a fault that
        ended it), riding again after a fault the loaded host caused (`excuse`): the session
        that got going and its status. `started`: a session already started after a `prepare`,
        its first try."""
        for _ in range(tries):
            if started is None:
                self.prepare()
                self._moving_late = late_steps(self.rider)
                started = start()
            status = going(started)
            if status.state not in FAULT_STATES:
                return started, status
            self.excuse(status)
            started = None
        raise AssertionError(f"the simulated world was late in {tries} rides in a row")

    def excuse(self, status: Status) -> None:
        """Asserts that `status` faulted for the loaded host, not for the daemon; the next
        `prepare` then calibrates the tilt again if its gain may be spoiled."""
        fault = status.fault
        assert status.state in FAULT_STATES and fault is not None, status
        if spoiled(status) or scan_stalled(status):  # the machine's own word on a stall
            return
        if fault.code is FaultCode.ROTATE_HOME_TIMEOUT:  # an edge a stall hid (the fast config)
            world_late = late_steps(self.rider) > self._moving_late
            assert world_late, f"neither the scan nor the world stalled: {status}"
            return
        assert fault.code in TILT_LATE_WORLD, status
        late = late_steps(self.rider)
        assert late > self._tilt_late, f"the simulated world was never late: {status}"
        self._redo_tilt = True


def prepare(rider: Rider, tries: int = 4) -> Status:
    """Calibrate what is not calibrated, then home, through the faults a loaded host causes
    (`Preparation`); the machine ends IDLE."""
    return Preparation(rider).prepare(tries)


def wait_revolutions(
    rider: Rider, reply: Reply, done: int, timeout: float = STEP_TIMEOUT_S
) -> Status:
    """Wait until the session `reply` started has completed `done` revolutions."""
    status = not_stalled(until_revolutions(rider, reply, done, timeout))
    assert status.state not in SETTLED, f"session ended early: {status}"
    return status


def until_revolutions(
    rider: Rider, reply: Reply, done: int, timeout: float = STEP_TIMEOUT_S
) -> Status:
    """The status once the session `reply` started has completed `done` revolutions, or the
    rest or fault state that ended it before."""
    deadline = time.monotonic() + timeout
    for update in rider.watch(("status",), timeout=timeout):
        if isinstance(update, Status) and update.time >= reply.timecode:
            if update.session is not None and update.session.revolutions_done >= done:
                return update
            if update.state in SETTLED:
                return update
        assert time.monotonic() < deadline, f"no {done} revolutions in {timeout:g} s"
    raise AssertionError(f"status went quiet before {done} revolutions")


def wait_cycles(rider: Rider, cycles: int, timeout: float = STEP_TIMEOUT_S) -> Status:
    """Wait on status heartbeats until the scan loop has run `cycles` more cycles."""
    return states_over(rider, cycles, timeout)[-1]


def states_over(rider: Rider, cycles: int, timeout: float = STEP_TIMEOUT_S) -> list[Status]:
    """Every status published while the scan loop runs `cycles` more cycles: after the one
    published last when it is called, which may still show what the previous command ended
    (run `random:178645`: the HOMING of an earlier test's Home, stopped a cycle before, was
    taken for a refused Home's)."""
    start = rider.status().cycle
    deadline = time.monotonic() + timeout
    seen: list[Status] = []
    for update in rider.watch(("status",), timeout=timeout):
        if isinstance(update, Status) and update.cycle > start:
            seen.append(update)
            if update.cycle >= start + cycles:
                return seen
        assert time.monotonic() < deadline, f"loop did not run {cycles} cycles in {timeout:g} s"
    raise AssertionError("status went quiet")


WORLD_LAG_S = 1.0
"""Under `machine supervise` the simulated world runs in the supervisor and takes the outputs
from the process image on its own step (sim/world.py): a status read at once may be ahead of it."""


def relays_off(rider: Rider) -> bool:
    """True when every relay output is off as published (at once: the status that says so was
    published in the same cycle) and in the simulated world (within `WORLD_LAG_S`)."""
    if not all(p.value is False for p in rider.io() if p.kind == "ro"):
        return False
    deadline = time.monotonic() + WORLD_LAG_S
    while any(rider.sim("world").relays.values()):
        if time.monotonic() > deadline:
            return False
        time.sleep(0.01)
    return True
