"""The test side of a crash writer (`persist_crash_writer.serve`): rounds that fork a writer, let
it report progress, SIGKILL it at a random moment and say how far it got."""

from __future__ import annotations

import os
import signal
import subprocess
import time

from tests.procs import REPO, LineReader


class Lines:
    """Lines from a child's stdout; every read is bounded by one overall deadline."""

    def __init__(self, proc: subprocess.Popen[bytes], deadline: float) -> None:
        assert proc.stdout is not None
        self.reader = LineReader(proc.stdout)
        self.deadline = deadline

    def next(self) -> str:
        left = self.deadline - time.monotonic()
        assert left > 0, "the crash writer stopped answering"
        line = self.reader.line(left)
        assert line is not None, "the crash writer exited"
        return line

    def word(self, expected: str) -> int:
        """The number after `expected` on the next line."""
        line = self.next()
        word, _, number = line.partition(" ")
        assert word == expected, f"expected {expected!r}, got {line!r}"
        return int(number) if number else 0


class CrashServer:
    """A running crash writer server; `with` starts it and always stops it (and any writer)."""

    def __init__(self, argv: list[str], tag: str, bound_s: float) -> None:
        """`tag`: the word of the writer's progress lines (`<tag> <index>`); `bound_s` bounds
        the whole run, so a hung child fails the test instead of hanging it."""
        self.proc = subprocess.Popen(argv, cwd=REPO, stdin=subprocess.PIPE, stdout=subprocess.PIPE)
        self.lines = Lines(self.proc, time.monotonic() + bound_s)
        self.tag = tag
        self._pid: int | None = None

    def __enter__(self) -> CrashServer:
        self.lines.word("ready")
        return self

    def __exit__(self, *exc: object) -> None:
        if self._pid is not None:
            os.kill(self._pid, signal.SIGKILL)
        assert self.proc.stdin is not None
        self.proc.stdin.close()
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(timeout=10)

    def kill_round(self, start: int, reports: int, delay_s: float) -> int:
        """Fork a writer from index `start`, wait for `reports` progress lines and `delay_s`
        more, SIGKILL it; the last index it reported (lines on their way at the kill count)."""
        assert self.proc.stdin is not None
        self.proc.stdin.write(f"go {start}\n".encode())
        self.proc.stdin.flush()
        self._pid = pid = self.lines.word("pid")
        last = start - 1
        for _ in range(reports):
            last = self.lines.word(self.tag)
        time.sleep(delay_s)  # picks the kill moment; waits for nothing
        os.kill(pid, signal.SIGKILL)
        while (line := self.lines.next()) != f"reaped {pid}":
            last = int(line.removeprefix(f"{self.tag} "))
        self._pid = None
        return last
