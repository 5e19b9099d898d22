"""The whole controller frozen at once — the supervisor, its daemon and the daemon's history
process — while the simulated plant (`sim.plant`, a process of its own) keeps its clock, and what
the drives do meanwhile (issue 53).

Two freezes, as a host does them:
- `SIGSTOP`: every controller process stopped by a signal (`kill -STOP <supervisor> <daemon>`);
- `CGROUP`: the controller's processes in a freezer cgroup of their own, frozen (what `docker
  pause` and `podman pause` do to a container; a host under memory pressure stops them alike).

Nothing of the controller runs: no scan, no watchdog thread, no output guard. The plant's
charge-pump relay is what cuts the drives, `hal.sim.charge_pump_timeout_s` after the pump's last
change. The plant is asked directly, over its socket: the supervisor that serves `sim/world` is
frozen too. Shared by tests/reliability/test_whole_freeze.py and bench/freeze.py.
"""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from enum import StrEnum
from pathlib import Path

from ride_machine.rider.client import Rider
from ride_machine.schema.commands import Reply
from ride_machine.schema.sim import SimWorldState
from ride_machine.schema.status import Status
from ride_machine.sim.plant import ENDPOINT, recv_frame, send_frame
from tests.freeze import TILT_DPS, child_of, image_relays, ready, replaced, ride_the_tilt
from tests.procs import Daemon, child_pids

FREEZER_V1 = Path("/sys/fs/cgroup/freezer")
UNIFIED = Path("/sys/fs/cgroup")


class Whole(StrEnum):
    SIGSTOP = "sigstop-all"
    CGROUP = "cgroup-freezer"


def plant_world(directory: Path, timeout: float = 2.0) -> SimWorldState:
    """The truth, from the plant itself (the socket named in its `directory`)."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
        sock.settimeout(timeout)
        sock.connect((directory / ENDPOINT).read_text())
        send_frame(sock, {"op": "world", "stamp": time.time()})
        answer = recv_frame(sock)
    assert "ok" in answer, answer
    return SimWorldState.model_validate(answer["ok"])


def plant_dir(supervisor: Daemon) -> Path:
    """Where `machine supervise --sim` keeps its plant's image and endpoint."""
    return supervisor.data_dir / "supervisor"


def controller_pids(supervisor: Daemon) -> list[int]:
    """The supervisor, its daemon and the daemon's children; not the plant."""
    daemon = child_of(supervisor)
    return [supervisor.proc.pid, daemon, *child_pids(daemon)]


class FreezerCgroup:
    """A freezer cgroup of the test's own (cgroup v1's freezer, or v2's `cgroup.freeze`)."""

    def __init__(self, name: str) -> None:
        self.v1 = FREEZER_V1.is_dir()
        self.path = (FREEZER_V1 if self.v1 else UNIFIED) / name
        self.path.mkdir(exist_ok=True)
        self.pids: list[int] = []

    @staticmethod
    def unavailable() -> str | None:
        """Why no freezer cgroup can be made here (None: it can)."""
        if os.geteuid() != 0:
            return "the cgroup freezer needs root"
        if FREEZER_V1.is_dir() or (UNIFIED / "cgroup.controllers").exists():
            return None
        return "no cgroup freezer on this host (neither v1's freezer nor cgroup v2)"

    def add(self, pids: list[int]) -> None:
        for pid in pids:
            (self.path / "cgroup.procs").write_text(str(pid))
        self.pids = pids

    def freeze(self) -> None:
        if self.v1:
            (self.path / "freezer.state").write_text("FROZEN")
        else:
            (self.path / "cgroup.freeze").write_text("1")

    def thaw(self) -> None:
        if self.v1:
            (self.path / "freezer.state").write_text("THAWED")
        else:
            (self.path / "cgroup.freeze").write_text("0")

    def close(self) -> None:
        """Thawed, its processes back where they came from, the cgroup gone."""
        with contextlib.suppress(OSError):
            self.thaw()
        home = self.path.parent / "cgroup.procs"
        for pid in self.pids:
            with contextlib.suppress(OSError):
                home.write_text(str(pid))
        with contextlib.suppress(OSError):
            self.path.rmdir()


@contextlib.contextmanager
def frozen(
    kind: Whole, first: list[int], rest: list[int], between: Callable[[], None]
) -> Iterator[float]:
    """The processes `first` and `rest` frozen for the block (in that order, microseconds
    apart); yields the monotonic time just before. Thawed in the same order, `between()` run
    once `first` runs again and `rest` does not yet: the supervisor wakes before its daemon, so
    what it does about the freeze (kill a daemon frozen past `--hang`) is not a race."""
    groups = (first, rest)
    if kind is Whole.SIGSTOP:
        t0 = time.monotonic()
        for pid in (*first, *rest):
            os.kill(pid, signal.SIGSTOP)
        try:
            yield t0
        finally:
            for n, group in enumerate(groups):
                for pid in group:
                    with contextlib.suppress(ProcessLookupError):
                        os.kill(pid, signal.SIGCONT)
                if n == 0:
                    between()
        return
    cgroups = [FreezerCgroup(f"ride-freeze-{os.getpid()}-{n}") for n in range(2)]
    try:
        for cgroup, group in zip(cgroups, groups, strict=True):
            cgroup.add(group)
        t0 = time.monotonic()
        for cgroup in cgroups:
            cgroup.freeze()
        yield t0
    finally:
        cgroups[0].close()
        between()
        cgroups[1].close()


@dataclass(frozen=True)
class WholeOutcome:
    """One freeze of the whole controller, as the plant lived it."""

    kind: Whole
    cut_s: float | None
    """From the freeze to the drives without power (None: powered throughout)."""
    overrun_deg: float
    """The tilt's travel past where it stood at the freeze."""
    relays_on: bool
    """The ride's relays still on in the image at the end of the freeze."""
    hold_s: float


def prepare_a_ride(supervisor: Daemon, rider: Rider) -> None:
    """Home, and drive the tilt towards 45°: returns once it is 5° into its move."""
    try:
        _ride(supervisor, rider)
    except AssertionError as exc:  # a trial that could not start: the supervisor's account
        raise AssertionError(f"{exc}\n--- supervisor log:\n{supervisor.log()[-5000:]}") from exc


def _ride(supervisor: Daemon, rider: Rider) -> None:
    ready(rider)

    def going(_: Reply) -> Status:
        tilt_moving(supervisor, rider)
        return rider.status()

    ride_the_tilt(rider, going)


def freeze_whole(supervisor: Daemon, rider: Rider, kind: Whole, hold_s: float) -> WholeOutcome:
    """Drive the tilt (`prepare_a_ride`), freeze the whole controller 5° into the move for
    `hold_s` (longer than the supervisor's `--hang`), and read the plant before thawing;
    returns once the frozen daemon was replaced and the new one answers."""
    prepare_a_ride(supervisor, rider)
    pids = controller_pids(supervisor)
    before = plant_world(plant_dir(supervisor))
    said = len(supervisor.log())

    def daemon_down() -> None:  # the supervisor's answer to a daemon frozen past --hang
        wait_for_log(supervisor, said, "event=daemon_down")

    with frozen(kind, pids[:1], pids[1:], daemon_down) as t0:
        deadline = t0 + hold_s
        while (left := deadline - time.monotonic()) > 0:
            time.sleep(left)  # the freeze itself: nothing of the controller runs meanwhile
        world = plant_world(plant_dir(supervisor))
        relays_on = any(image_relays(supervisor.data_dir).values())
    assert before.clock is not None and world.clock is not None
    cut = None
    if world.drives_powered is False and world.drives_off_s is not None:
        cut = world.clock - world.drives_off_s - t0
    overrun = world.tilt_deg - (before.tilt_deg + TILT_DPS * (t0 - before.clock))
    replaced(supervisor, rider, pids[1])
    return WholeOutcome(kind, cut, overrun, relays_on, hold_s)


def wait_for_log(daemon: Daemon, start: int, text: str, timeout: float = 20.0) -> str:
    """The log from character `start` once it holds `text` (bounded)."""
    deadline = time.monotonic() + timeout
    while text not in (said := daemon.log()[start:]):
        assert time.monotonic() < deadline, f"no {text!r} in:\n{said[-3000:]}"
        time.sleep(0.02)
    return said


def tilt_moving(supervisor: Daemon, rider: Rider, timeout: float = 30.0) -> SimWorldState | None:
    """The plant once the tilt is driven 5° into its move; None if the move ended first."""
    deadline = time.monotonic() + timeout
    while True:
        world = plant_world(plant_dir(supervisor))
        if world.tilt_deg >= 5.0 and world.relays.get("O_3"):
            return world
        status = rider.status()
        if status.fault is not None:
            return None
        assert time.monotonic() < deadline, f"the tilt never moved: {world}"
        time.sleep(0.01)
