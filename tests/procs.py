"""Real processes for integration tests: a daemon on a free loopback port, and clean-up."""

from __future__ import annotations

import contextlib
import os
import random
import select
import signal
import socket
import subprocess
import sys
import tempfile
import time
import weakref
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

from ride_machine.rider.client import Rider
from ride_machine.service.signals import STACKS_SIGNAL
from ride_machine.service.supervision.procstate import describe, threads

REPO = Path(__file__).resolve().parent.parent
START_TIMEOUT_S = 20.0
STOP_TIMEOUT_S = 10.0
LOG_WAIT_S = 5.0

HOST_CONFIG = """\
# `machine run` in a test that gives no --config: the project defaults, but for the watchdog.
# A shared 2-core CI host stalls a scan thread for 30-90 ms now and then; the default limit
# (3 periods, 30 ms) then trips, and a watchdog FAULT_HW and event appear in a test that is
# not about the watchdog (seen: `?last=1` answered with the watchdog event instead of
# daemon_start). Tests of the watchdog itself give their own config.
[loop]
watchdog_periods = 100
"""

ZENOH_TEST_CONFIG = """{
  mode: "peer",
  scouting: { multicast: { enabled: false }, gossip: { enabled: false } },
  transport: { link: { tx: { lease: 1000, keep_alive: 4 } } },
}
"""


def stop_process(
    proc: subprocess.Popen[Any], sig: int = signal.SIGTERM, timeout: float = STOP_TIMEOUT_S
) -> int:
    """Signal, wait (bounded), then kill: a child process never outlives its test."""
    if proc.poll() is None:
        proc.send_signal(sig)
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout)
    return proc.returncode


class LineReader:
    """A child's output line by line, every read bounded.

    It reads the pipe itself: a `select()` on the pipe followed by a buffered `readline()`
    misses a line when two came in one read (the second waits in Python's buffer while the
    pipe looks empty), which stalled a benchmark for its whole timeout on a loaded host.
    """

    def __init__(self, stream: IO[Any]) -> None:
        self.fd = stream.fileno()
        self.buf = b""
        self.eof = False

    def line(self, timeout: float) -> str | None:
        """The next line without its newline; None once the child closed its end; raises
        TimeoutError when no whole line came within `timeout` seconds."""
        deadline = time.monotonic() + timeout
        while b"\n" not in self.buf:
            if self.eof:
                rest, self.buf = self.buf, b""
                return rest.decode() if rest else None
            ready, _, _ = select.select([self.fd], [], [], max(0.0, deadline - time.monotonic()))
            if not ready:
                raise TimeoutError(f"no whole line within {timeout:g} s (have {self.buf[-200:]!r})")
            chunk = os.read(self.fd, 65536)
            self.eof = not chunk
            self.buf += chunk
        text, self.buf = self.buf.split(b"\n", 1)
        return text.decode()


PORTS = (20_000, 32_000)
"""Where the tests' listeners are placed: below Linux's ephemeral range (32768-60999), which the
kernel hands to outgoing connections. A port the kernel chose for a listener (bind to 0) comes
from that range, and on a busy run another test's connection could take it before the daemon
bound it (run 51: a daemon's `Address already in use`)."""
PORT_CLAIMS = Path(tempfile.gettempdir()) / "ride-test-ports"
"""One file per port handed out: two test processes (xdist workers, a benchmark's children)
never get the same port while either may still use it."""
PORT_CLAIM_S = 900.0
"""After this a claim is stale (its holder is long done) and the port may be handed out again."""
_pick = random.SystemRandom()


def sigstop(pid: int, timeout: float = 10.0) -> None:
    """Stop `pid` (SIGSTOP) and return once every thread of it is stopped. The kernel stops a
    process's threads as each is next scheduled: on a busy host one of them ran on after
    `kill` returned (run 53: a Home sent after the SIGSTOP was taken 1 ms later)."""
    os.kill(pid, signal.SIGSTOP)
    deadline = time.monotonic() + timeout
    while not all(t.state in "tT" for t in threads(pid)):
        if time.monotonic() > deadline:
            raise TimeoutError(f"pid {pid} not stopped in {timeout:g} s: {describe(threads(pid))}")
        time.sleep(0.001)  # the kernel's thread states: no event tells of them


def free_port() -> int:
    """A port on 127.0.0.1 that nothing listens on and no other test process was given."""
    PORT_CLAIMS.mkdir(exist_ok=True)
    for _ in range(1000):
        port = _pick.randrange(*PORTS)
        if not _claim(port):
            continue
        with socket.socket() as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue  # something outside the tests listens there: its claim stays
        return port
    raise RuntimeError(f"no free port in {PORTS} (claims in {PORT_CLAIMS})")


def _claim(port: int) -> bool:
    """Claim `port` for this process: its file made, or a stale one taken over (a rename has
    one winner)."""
    path = PORT_CLAIMS / str(port)
    for _ in range(2):
        try:
            os.close(os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY))
            return True
        except FileExistsError:
            try:
                if time.time() - path.stat().st_mtime < PORT_CLAIM_S:
                    return False
                stale = path.with_name(f"{port}.{os.getpid()}")
                os.rename(path, stale)
                stale.unlink()
            except FileNotFoundError:
                return False  # another process took it over first
    return False


def write_zenoh_config(directory: Path) -> Path:
    path = directory / "zenoh-test.json5"
    path.write_text(ZENOH_TEST_CONFIG)
    return path


STACKS_WAIT_S = 2.0
STACKS_SETTLE_S = 0.2
STACKS_MARK = "(most recent call first)"
"""How `faulthandler` heads each thread's stack."""


def catches(pid: int, sig: int) -> bool:
    """Whether process `pid` has a handler for `sig` (its `SigCgt` mask in /proc)."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return False
    mask = next(
        (line.split()[1] for line in status.splitlines() if line.startswith("SigCgt:")), "0"
    )
    return bool(int(mask, 16) >> (sig - 1) & 1)


@dataclass
class Daemon:
    """A `machine run` child process; `stop()` sends SIGTERM and waits (bounded)."""

    proc: subprocess.Popen[str]
    endpoint: str
    machine_id: str
    data_dir: Path
    zenoh_config: Path
    log_path: Path
    extra: list[str] = field(default_factory=list)
    started: float = field(default_factory=time.time)

    def __post_init__(self) -> None:
        _STARTED[:] = [ref for ref in _STARTED if ref() is not None]
        _STARTED.append(weakref.ref(self))

    def rider(self, **kwargs: object) -> Rider:
        return Rider(
            self.machine_id,
            connect=[self.endpoint],
            zenoh_config_path=self.zenoh_config,
            **kwargs,  # type: ignore[arg-type]
        )

    def cli(self, *args: str, timeout: float = 60.0) -> subprocess.CompletedProcess[str]:
        """`rider … ARGS` against this daemon (its endpoint, config and id), bounded."""
        return self.run_rider("--machine", self.machine_id, *args, timeout=timeout)

    def run_rider(self, *args: str, timeout: float = 60.0) -> subprocess.CompletedProcess[str]:
        """`rider --connect ENDPOINT --zenoh-config CONFIG ARGS` against this daemon, no machine
        named (the README's way), bounded."""
        linked = ("--connect", self.endpoint, "--zenoh-config", str(self.zenoh_config))
        return run_rider(*linked, *args, timeout=timeout)

    def log(self) -> str:
        return self.log_path.read_text() if self.log_path.exists() else ""

    def has_logged(self, text: str, timeout: float = LOG_WAIT_S) -> bool:
        """Whether a line with `text` reaches the log within `timeout`: lines are written by the
        daemon's log writer thread, a moment after what they tell (service/logfmt.py)."""
        deadline = time.monotonic() + timeout
        while text not in self.log():
            if time.monotonic() > deadline:
                return False
            time.sleep(0.02)
        return True

    def stop(self, sig: int = signal.SIGTERM) -> int:
        return stop_process(self.proc, sig)

    def stacks(self, timeout: float = STACKS_WAIT_S) -> list[str]:
        """Every thread's stack, as the running process writes it to its log when asked
        (`STACKS_SIGNAL`, service/signals.py); [] when it does not catch that signal (yet: it
        is caught from the config's load on, and would kill the process before) or wrote
        nothing within `timeout` (a process stopped by SIGSTOP)."""
        if not catches(self.proc.pid, STACKS_SIGNAL):
            return []
        start = len(self.log())
        os.kill(self.proc.pid, STACKS_SIGNAL)
        deadline = time.monotonic() + timeout
        while STACKS_MARK not in self.log()[start:]:
            if time.monotonic() > deadline:
                return []
            time.sleep(0.02)
        time.sleep(STACKS_SETTLE_S)  # the handler writes thread after thread
        lines = self.log()[start:].splitlines()
        first = next(i for i, line in enumerate(lines) if STACKS_MARK in line)
        return lines[max(first - 1, 0) :]


_STARTED: list[weakref.ref[Daemon]] = []
"""The daemons this test process started, for the logs of a failed test (`logs_since`): weak, so
a test's process (and its pipes) goes when the test lets go of it; a failed test's traceback
and the fixtures in use hold theirs."""

LOG_TAIL_LINES = 40


def logs_since(since: float) -> list[tuple[str, str]]:
    """(title, last lines) of each daemon's log that may tell why a test failed: those still
    running, and those started since `since` (a test's own, stopped by now)."""
    sections = []
    for ref in _STARTED:
        daemon = ref()
        if daemon is None or (daemon.proc.poll() is not None and daemon.started < since):
            continue
        lines = daemon.log().splitlines()[-LOG_TAIL_LINES:]
        title = f"daemon {daemon.machine_id} (pid {daemon.proc.pid}) log, last {len(lines)} lines"
        sections.append((title, "\n".join(line[:400] for line in lines)))
        if daemon.proc.poll() is None and (stacks := daemon.stacks()):
            title = f"daemon {daemon.machine_id} (pid {daemon.proc.pid}), its threads' stacks"
            sections.append((title, "\n".join(line[:400] for line in stacks)))
    return sections


def child_pids(pid: int) -> list[int]:
    """The pids of the children of process `pid` (pgrep -P), bounded."""
    done = run_bounded(["pgrep", "-P", str(pid)], timeout=10)
    return [int(child) for child in done.stdout.split()]


def children_running(pid: int, module: str) -> list[int]:
    """The children of `pid` that run `python -m <module>` (a supervisor's daemon is
    `service.cli`, its simulated plant `sim.plant`)."""
    out = []
    for child in child_pids(pid):
        try:
            argv = Path(f"/proc/{child}/cmdline").read_bytes().split(b"\0")
        except OSError:  # gone meanwhile
            continue
        if module.encode() in argv:
            out.append(child)
    return out


def machine_cmd(*args: str) -> list[str]:
    return [sys.executable, "-m", "ride_machine.service.cli", *args]


def rider_cmd(*args: str) -> list[str]:
    return [sys.executable, "-m", "ride_machine.rider.cli", *args]


def run_rider(*args: str, timeout: float = 60.0) -> subprocess.CompletedProcess[str]:
    """`rider ARGS` from the repository, its output captured, bounded."""
    return run_bounded(rider_cmd(*args), timeout=timeout)


def run_machine(
    *args: str, cwd: Path = REPO, env: dict[str, str] | None = None, timeout: float = 60.0
) -> subprocess.CompletedProcess[str]:
    """`machine ARGS` in `cwd` (with only `env`, when given), its output captured, bounded."""
    return run_bounded(machine_cmd(*args), timeout=timeout, cwd=cwd, env=env)


def run_bounded(
    cmd: list[str], timeout: float, cwd: Path = REPO, env: dict[str, str] | None = None
) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        cmd, check=False, capture_output=True, text=True, timeout=timeout, cwd=cwd, env=env
    )


def start_daemon(  # noqa: PLR0913 - keyword options of one test helper, each defaulted
    tmp: Path,
    machine_id: str = "m1",
    *,
    extra: list[str] | None = None,
    port: int | None = None,
    netns: str | None = None,
    listen_host: str = "127.0.0.1",
    wait: bool = True,
    pipe: bool = False,
    env: dict[str, str] | None = None,
) -> Daemon:
    """Start `machine run --sim` and wait until its liveliness token is seen.

    Without a `--config` in `extra` the daemon runs on `HOST_CONFIG` (the defaults, a watchdog
    that tolerates a loaded host). `pipe`: its output goes to a pipe (`proc.stdout`) the caller
    reads, or leaves unread, instead of to its log file. `env`: added to its environment."""
    port = port or free_port()
    endpoint = f"tcp/{listen_host}:{port}"
    data_dir = tmp / f"data-{machine_id}"
    zconf = write_zenoh_config(tmp)
    log_path = tmp / f"daemon-{machine_id}.log"
    cmd = machine_cmd(
        "run",
        "--sim",
        "--id",
        machine_id,
        "--zenoh-config",
        str(zconf),
        "--listen",
        endpoint,
        "--data-dir",
        str(data_dir),
        *(extra or []),
    )
    if "--config" not in (extra or []):
        host_config = tmp / "machine-host.toml"
        host_config.write_text(HOST_CONFIG)
        cmd += ["--config", str(host_config)]
    if netns:
        cmd = ["ip", "netns", "exec", netns, *cmd]
    env = {**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})}
    with log_path.open("w") as log:
        proc = subprocess.Popen(
            cmd,
            stdout=subprocess.PIPE if pipe else log,
            stderr=subprocess.STDOUT,
            text=True,
            cwd=REPO,
            env=env,
        )
    daemon = Daemon(proc, endpoint, machine_id, data_dir, zconf, log_path, extra or [])
    if wait:
        try:
            wait_alive(daemon)
        except BaseException:
            daemon.stop(signal.SIGKILL)
            raise
    return daemon


def wait_alive(daemon: Daemon, timeout: float = START_TIMEOUT_S) -> None:
    """Block until the daemon answers a status query (its liveliness token as the event)."""
    with daemon.rider(timeout=1.0) as r:
        for change in r.follow_machines(timeout=0.2):
            if change == (daemon.machine_id, True):
                break
            if daemon.proc.poll() is not None:
                raise RuntimeError(f"daemon exited with {daemon.proc.returncode}:\n{daemon.log()}")
            if change is None:
                timeout -= 0.2
                if timeout <= 0:
                    raise TimeoutError(f"daemon not alive in time:\n{daemon.log()}")
        r.status(timeout=5.0)


@contextlib.contextmanager
def running_daemon(tmp: Path, machine_id: str = "m1", **kwargs: object) -> Iterator[Daemon]:
    daemon = start_daemon(tmp, machine_id, **kwargs)  # type: ignore[arg-type]
    try:
        yield daemon
    finally:
        daemon.stop()


def run_module(module: str, *args: object, timeout: float) -> str:
    """`python -m <module> <args>` in the repo, bounded by `timeout`: its stdout, once it has
    exited 0 (else the assertion shows the end of both streams)."""
    proc = subprocess.run(
        [sys.executable, "-m", module, *map(str, args)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=timeout,
        check=False,
    )
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    return proc.stdout


GLIBC_HEAP_BYTES = 64 << 20
"""glibc reserves each thread arena's heap as one block of this size, aligned to it (64-bit)."""


def malloc_arenas(pid: int) -> int:
    """glibc malloc arenas of a process, the main one included, read from /proc/<pid>/maps.

    A thread arena's heap is an anonymous mapping at an address aligned to 64 MiB, its used
    part read-write and the rest reserved (`---p`) up to 64 MiB: counted from outside, so a
    test or a benchmark can check any process."""
    maps: list[tuple[int, int, str, bool]] = []
    with open(f"/proc/{pid}/maps") as fh:
        for line in fh:
            parts = line.split()
            lo, hi = (int(x, 16) for x in parts[0].split("-"))
            maps.append((lo, hi, parts[1], len(parts) > 5))
    heaps = 0
    for i, (lo, hi, perms, named) in enumerate(maps):
        if named or not perms.startswith("rw") or lo % GLIBC_HEAP_BYTES:
            continue
        end = hi
        if i + 1 < len(maps):
            nlo, nhi, nperms, nnamed = maps[i + 1]
            if nlo == hi and nperms.startswith("---") and not nnamed:
                end = nhi
        heaps += end - lo == GLIBC_HEAP_BYTES
    return 1 + heaps
