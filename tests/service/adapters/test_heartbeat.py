"""The heartbeat file (service/adapters/heartbeat.py): touched only while the loop cycles."""

from __future__ import annotations

import os
import time
from pathlib import Path

from ride_machine.service.adapters.heartbeat import HEARTBEAT_FILE_ENV, HeartbeatFile

OLD = 1_000_000.0
"""An mtime far in the past: a touch is seen as the mtime leaving it."""


def test_the_file_is_touched_only_when_the_loop_has_cycled(tmp_path: Path) -> None:
    count = [0]
    beat = HeartbeatFile(tmp_path / "hb", lambda: count[0])
    assert not beat.tick()  # the first look only records the counter
    assert not (tmp_path / "hb").exists()
    count[0] = 5
    assert beat.tick()
    os.utime(tmp_path / "hb", (OLD, OLD))
    assert not beat.tick()  # a stalled loop: the file ages
    assert (tmp_path / "hb").stat().st_mtime == OLD
    count[0] = 6
    assert beat.tick()
    assert (tmp_path / "hb").stat().st_mtime > OLD
    assert beat.touched == 2


def test_a_file_that_cannot_be_written_is_reported_not_raised(tmp_path: Path) -> None:
    count = [0]
    beat = HeartbeatFile(tmp_path / "missing-dir" / "hb", lambda: count[0])
    beat.tick()
    count[0] = 1
    assert not beat.tick()
    assert beat.touched == 0


def test_the_thread_touches_while_cycling_and_stop_removes_the_file(tmp_path: Path) -> None:
    path = tmp_path / "hb"
    start = time.monotonic()
    beat = HeartbeatFile(path, lambda: int((time.monotonic() - start) * 100), interval_s=0.01)
    beat.start()
    try:
        deadline = time.monotonic() + 10.0
        while beat.touched < 3:
            assert time.monotonic() < deadline, "never touched"
            time.sleep(0.01)
        assert path.exists()
    finally:
        beat.stop()
    assert not path.exists()


def test_only_the_environment_variable_turns_it_on(tmp_path: Path) -> None:
    assert HeartbeatFile.from_env(lambda: 0, env={}) is None
    assert HeartbeatFile.from_env(lambda: 0, env={HEARTBEAT_FILE_ENV: " "}) is None
    beat = HeartbeatFile.from_env(lambda: 0, env={HEARTBEAT_FILE_ENV: str(tmp_path / "hb")})
    assert beat is not None and beat.path == tmp_path / "hb"
