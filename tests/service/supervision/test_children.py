"""The child keeper when a killed daemon does not die: one stuck in the kernel (D state: a hung
disk, piControl) outlives every bounded wait, and supervision goes on; a stop ends cleanly.

The child is a stand-in with `Popen`'s calls, whose `wait` always times out, as it does for a
process in D state; nothing is started."""

from __future__ import annotations

import queue
import signal
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import cast

import pytest

from ride_machine.service.bus.supervisor import SupervisorBus
from ride_machine.service.core.scan.beat import BeatReader
from ride_machine.service.supervision.children import ChildKeeper
from ride_machine.service.supervision.outcome import EXIT_OK
from ride_machine.service.supervision.outputguard import Stall
from ride_machine.service.supervision.restarts import (
    Child,
    Happening,
    Kind,
    SupervisorOptions,
)

NO_SUCH_PID = 999_999_999
"""Above any kernel's pid_max: /proc has nothing for it (procstate reads no thread)."""


@dataclass
class StuckProc:
    """A process in D state as `Popen` shows it: running, and no wait ever ends."""

    did: list[str]
    pid: int = NO_SUCH_PID
    waits: list[float] = field(default_factory=list)

    def poll(self) -> int | None:
        return None

    def wait(self, timeout: float | None = None) -> int:
        self.waits.append(timeout or 0.0)
        raise subprocess.TimeoutExpired("machine run", timeout or 0.0)

    def send_signal(self, sig: int) -> None:
        self.did.append(signal.Signals(sig).name)

    def kill(self) -> None:
        self.did.append("SIGKILL")


@dataclass
class Bus:
    """What the keeper tells the machine's bus."""

    down: list[str] = field(default_factory=list)

    def daemon_down(self, reason: str) -> None:
        self.down.append(reason)

    def daemon_up(self) -> None:
        pass

    def republish(self) -> None:
        pass


def keeper_of(tmp_path: Path, did: list[str]) -> tuple[ChildKeeper, StuckProc, Bus]:
    """A keeper whose child is up and stuck; `did` gets the signals and the safe writes."""
    proc, bus = StuckProc(did), Bus()
    keeper = ChildKeeper(
        SupervisorOptions(),
        tmp_path,
        (cast(BeatReader, None), -1),
        queue.SimpleQueue(),
        cast(SupervisorBus, bus),
        lambda: did.append("safe"),
        None,
        heartbeat_s=60.0,
    )
    child = Child(cast(subprocess.Popen[bytes], proc), 1, time.monotonic())
    child.up_since = child.started
    keeper.child, keeper.generation = child, 1
    return keeper, proc, bus


@pytest.mark.parametrize(
    ("happening", "when"),
    [
        (Happening(Kind.PRESENCE, present=False), "gone_from_bus"),
        (Happening(Kind.HUNG, stall=Stall(NO_SUCH_PID, 1, 1.0, energised=False)), "hung"),
    ],
)
@pytest.mark.hazard("H04")
def test_a_child_that_outlives_its_kill_leaves_supervision_running(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, happening: Happening, when: str
) -> None:
    did: list[str] = []
    keeper, proc, bus = keeper_of(tmp_path, did)
    keeper.happenings.put(happening)
    keeper.happenings.put(Happening(Kind.STOP))
    assert keeper.keep() == EXIT_OK  # the stop after it is still heard
    assert "SIGKILL" in did and "safe" in did
    assert bus.down and keeper.child is None  # reported, and a restart scheduled
    assert proc.waits and max(proc.waits) <= keeper.options.stop_timeout_s  # every wait bounded
    assert f"event=child_kill_pending pid={NO_SUCH_PID} when={when}" in caplog.text


def test_a_stop_that_outlasts_sigterm_and_sigkill_ends_cleanly(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    did: list[str] = []
    keeper, proc, _ = keeper_of(tmp_path, did)
    keeper.stop()
    assert did == ["SIGTERM", "SIGKILL"]
    assert proc.waits == [keeper.options.stop_timeout_s] * 2  # each wait bounded
    assert "event=child_stop_timeout" in caplog.text
    assert "event=child_kill_pending" in caplog.text and "when=stop" in caplog.text


def test_a_frozen_child_is_killed_at_once_at_stop_outputs_safe_first(tmp_path: Path) -> None:
    did: list[str] = []
    keeper, _, _ = keeper_of(tmp_path, did)
    keeper.stop(frozen=True)
    assert did == ["safe", "SIGKILL"]  # no SIGTERM it could not answer, no 10 s wait for it


def test_the_keepers_loop_says_when_it_last_came_round(tmp_path: Path) -> None:
    keeper, _, _ = keeper_of(tmp_path, [])
    keeper.happenings.put(Happening(Kind.STOP))
    before = time.monotonic()
    keeper.keep()
    assert keeper.turned >= before
    assert keeper.turning(keeper.turned + keeper.turn_limit_s)
    assert not keeper.turning(keeper.turned + keeper.turn_limit_s + 0.001)
