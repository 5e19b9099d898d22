"""A `machine run --sim` child for benchmarks: loop tuning, a calibrated start, clean stops."""

from __future__ import annotations

import contextlib
import functools
import os
import tempfile
import tomllib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from ride_machine.rider.client import CommandRefused, Rider
from ride_machine.schema.status import MachineState
from ride_machine.service.core.storage.persist import CALIBRATION_FILE
from tests.procs import Daemon, start_daemon

STATS_WINDOW = 100_000
"""The largest diag window: a 60 s run at 1 ms fits, so diag percentiles cover the whole run."""


@dataclass(frozen=True)
class Tuning:
    """The real-time options of the `[loop]` config section for one run."""

    spin_s: float = 0.0
    gc_freeze: bool = True
    cpu: int | None = None
    rt_priority: int | None = None
    cpus: tuple[int, ...] | None = None
    """`loop.cpus`: the whole daemon pinned."""
    zenoh_threads: int | None = None
    """`bus.zenoh_threads` (None: the default, one)."""
    kernel_slice: bool = False
    """`loop.slice_s = 0`: the daemon's threads on the kernel's time slice, not a short one."""

    def changed(self) -> list[tuple[str, str, str]]:
        """Each option set away from the config's default: its section, its line there, and
        how a table names it."""
        options = [
            ("loop", f"spin_s = {self.spin_s!r}", f"spin {self.spin_s * 1e3:g} ms", self.spin_s),
            ("loop", "gc_freeze = false", "no gc_freeze", not self.gc_freeze),
            ("loop", f"cpu = {self.cpu}", f"pinned cpu {self.cpu}", self.cpu is not None),
            (
                "loop",
                f"cpus = {list(self.cpus or ())}",
                f"daemon on cpus {'+'.join(map(str, self.cpus or ()))}",
                self.cpus is not None,
            ),
            (
                "loop",
                f"rt_priority = {self.rt_priority}",
                f"SCHED_FIFO {self.rt_priority}",
                self.rt_priority is not None,
            ),
            (
                "bus",
                f"zenoh_threads = {self.zenoh_threads}",
                f"zenoh_threads {self.zenoh_threads}",
                self.zenoh_threads is not None,
            ),
            ("loop", "slice_s = 0", "kernel time slice", self.kernel_slice),
        ]
        return [(section, line, label) for section, line, label, on in options if on]

    def label(self) -> str:
        return ", ".join(label for _, _, label in self.changed()) or "defaults"

    def lines(self, section: str) -> list[str]:
        """The config lines of the options set in `section` (`loop` or `bus`)."""
        return [line for where, line, _ in self.changed() if where == section]


def pinnable_cpu() -> int | None:
    """A CPU to pin a whole process to (`loop.cpus`): the last one this process may use, or
    None with a single CPU (pinning would change nothing)."""
    cpus = os.sched_getaffinity(0)
    return max(cpus) if len(cpus) > 1 else None


def config_toml(
    period_s: float,
    tuning: Tuning,
    heartbeat_s: float | None = None,
    watchdog_periods: int | None = None,
    events: bool = True,
    events_thread: bool = False,
) -> str:
    lines = [
        "[loop]",
        f"period_s = {period_s!r}",
        f"stats_window = {STATS_WINDOW}",
        *tuning.lines("loop"),
    ]
    if watchdog_periods is not None:
        lines.append(f"watchdog_periods = {watchdog_periods}")
    bus = [] if heartbeat_s is None else [f"heartbeat_s = {heartbeat_s!r}"]
    bus += tuning.lines("bus")
    if bus:
        lines += ["", "[bus]", *bus]
    if not events:
        lines += ["", "[events]", "enabled = false"]
    elif events_thread:
        lines += ["", "[events]", "process = false"]
    return "\n".join(lines) + "\n"


@functools.cache
def calibration_file(config_toml: str = "") -> bytes:
    """What a calibration run of the simulator stores (found once, with a fake clock): the
    default machine's, or that of the machine `config_toml` describes. A daemon must run on
    its own machine's calibration: the revolution check refuses another's revolution time."""
    from ride_machine.service.config.model import MachineConfig
    from tests.rig import Rig

    config = MachineConfig.model_validate(tomllib.loads(config_toml))
    with tempfile.TemporaryDirectory() as tmp:
        rig = Rig(config=config, data_dir=Path(tmp))
        rig.calibrate()
        return (Path(tmp) / CALIBRATION_FILE).read_bytes()


@contextlib.contextmanager
def bench_daemon(
    period_s: float = 0.010,
    tuning: Tuning = Tuning(),
    *,
    calibrated: bool = False,
    heartbeat_s: float | None = None,
    watchdog_periods: int | None = None,
    events: bool = True,
    events_thread: bool = False,
    machine_id: str = "m1",
) -> Iterator[Daemon]:
    """A daemon on a free loopback port in its own temp dir; stopped (bounded) on exit.
    `events=False`: without the event history (`[events] enabled = false`); `events_thread`:
    the history written by a thread of the daemon (`[events] process = false`)."""
    with tempfile.TemporaryDirectory(prefix="bench-") as tmp_name:
        tmp = Path(tmp_name)
        config = tmp / "machine.toml"
        config.write_text(
            config_toml(period_s, tuning, heartbeat_s, watchdog_periods, events, events_thread)
        )
        if calibrated:
            data = tmp / f"data-{machine_id}"
            data.mkdir()
            (data / CALIBRATION_FILE).write_bytes(calibration_file())
        daemon = start_daemon(tmp, machine_id, extra=["--config", str(config)])
        try:
            yield daemon
        finally:
            daemon.stop()


HOME_TRIES = 5


def home_and_start(rider: Rider, timeout: float = 30.0) -> list[str]:
    """Home a calibrated machine, then start the default session (relays on, axes moving).

    On a busy host a stalled scan can trip the watchdog or make homing miss the switch
    (FAULT_HW), also between homing and the start: home again, a few times; returns the
    faults seen on the way.
    """
    faults: list[str] = []
    for _ in range(HOME_TRIES):
        try:
            reply = rider.home()
        except CommandRefused as exc:
            # The watchdog publishes its FAULT_HW at once, from its own thread; a Home sent on
            # that status can reach the loop before its next cycle takes the fault (still
            # HOMING). Wait for the fault (or the end of homing) and try again.
            faults.append(str(exc.error.code))
            rider.wait_for([MachineState.IDLE, MachineState.FAULT_HW], timeout=timeout)
            continue
        status = rider.wait_for(
            [MachineState.IDLE, MachineState.FAULT_HW], timeout=timeout, after=reply.timecode
        )
        if status.state is MachineState.IDLE:
            try:
                rider.start()
            except CommandRefused as exc:  # a stall tripped the watchdog after homing
                faults.append(str(exc.error.code))
                continue
            return faults
        faults.append(str(status.fault.code if status.fault else status.state))
    raise HomingFailed(faults)


class HomingFailed(RuntimeError):
    """Homing kept faulting; `faults` says how."""

    def __init__(self, faults: list[str]) -> None:
        super().__init__(f"homing failed {len(faults)} times: {', '.join(faults)}")
        self.faults = faults
