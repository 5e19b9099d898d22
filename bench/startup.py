"""Start-up: how soon each entry point has done its job, from exec (issue 59).

Three things an operator waits for, each against its floor measured in the same run, the
variants interleaved round by round so a busy spell of the host falls on all of them alike:

- `rider --help`, beside `python -c pass` (the interpreter's own start and exit);
- a loopback `rider status` against a running daemon (simulator, 10 ms loop), with the machine
  named (`-m m1`) and without (the default: discovery settles first, rider/discovery.py's
  `SETTLE_S`), beside a bare Zenoh read of the same key from a fresh interpreter (import
  zenoh, open a session, one `get`, close: what any Python client pays);
- exec → the first command served: `machine run --sim` started cold in a fresh data directory,
  polled with a CheckHome (a read-only command the scan loop answers) until one is answered,
  beside a bare Zenoh queryable in a fresh interpreter on the same key. The daemon connects to
  this process's listening session, so its first reply is seen as soon as it is given.

Each process is timed from just before `Popen` to its exit (or its first reply); the daemon's
log dates its own steps (the bus up, the loop running) on the same wall clock.
"""

from __future__ import annotations

import contextlib
import io
import itertools
import os
import re
import subprocess
import sys
import tarfile
import tempfile
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path

import zenoh

from bench import common
from bench.common import ms
from bench.daemon import bench_daemon
from ride_machine.rider.discovery import SETTLE_S
from ride_machine.rider.link import zenoh_config
from tests.procs import REPO, free_port, machine_cmd, stop_process, write_zenoh_config

HELP_TARGET_S = 0.15
STATUS_TARGET_S = 0.3
SERVED_TARGET_S = 1.0
SERVE_TIMEOUT_S = 30.0
POLL_S = 0.002
"""Pause between two polls that found no queryable (a get to a key nobody serves returns at
once)."""
REPLY_WAIT_S = 2.0
"""A poll's own timeout: once a queryable is there, its reply is awaited, not cut short."""
CHECK_KEY = "machine/{id}/cmd/check/home"

BARE_READ = """
import sys, zenoh
conf = zenoh.Config.from_file(sys.argv[1])
conf.insert_json5("connect/endpoints", '["' + sys.argv[2] + '"]')
with zenoh.open(conf) as session:
    replies = [r for r in session.get(sys.argv[3], timeout=2.0) if r.ok is not None]
sys.exit(0 if replies else 3)
"""
"""A fresh interpreter's bare Zenoh read: config file, endpoint, key."""

BARE_SERVE = """
import sys, threading, zenoh
conf = zenoh.Config.from_file(sys.argv[1])
conf.insert_json5("connect/endpoints", '["' + sys.argv[2] + '"]')
with zenoh.open(conf) as session:
    session.declare_queryable(sys.argv[3], lambda query: query.reply(query.key_expr, b"ok"))
    threading.Event().wait()
"""
"""A fresh interpreter's bare Zenoh server: it answers `key` until it is stopped."""


def rider_script() -> list[str]:
    """The `rider` console script beside this interpreter, as an operator runs it."""
    script = Path(sys.executable).with_name("rider")
    if script.exists():
        return [sys.executable, str(script)]
    return [sys.executable, "-m", "ride_machine.rider.cli"]


def timed_run(cmd: list[str], cwd: Path = REPO, env: dict[str, str] | None = None) -> float:
    """Wall time of `cmd` from exec to exit; RuntimeError when it fails."""
    began = time.perf_counter()
    done = subprocess.run(
        cmd, capture_output=True, text=True, check=False, timeout=60, cwd=cwd, env=env
    )
    took = time.perf_counter() - began
    if done.returncode != 0:
        raise RuntimeError(f"{cmd[-1]} exited {done.returncode}: {done.stderr[-1000:]}")
    return took


def interleaved(runs: int, variants: dict[str, Callable[[], float]]) -> dict[str, common.Dist]:
    """`runs` rounds, each variant once per round in turn."""
    samples: dict[str, list[float]] = {name: [] for name in variants}
    for _ in range(runs):
        for name, once in variants.items():
            samples[name].append(once())
    return {name: common.Dist.of(s) for name, s in samples.items()}


def load_now() -> str:
    """The host's 1-minute load average, for a table's note."""
    return f"{os.getloadavg()[0]:.2f}"


# -------------------------------------------------------------------- exec → first served
class Listener:
    """This process's listening session, which a started server connects to and polls."""

    def __init__(self, zconf: Path) -> None:
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.session = zenoh.open(zenoh_config(zconf, [], [self.endpoint]))
        self._ids = itertools.count()

    def first_reply(self, proc: subprocess.Popen[str], key: str, began: float) -> float:
        """Seconds from `began` to the first reply on `key` (polling until one comes)."""
        while True:
            payload = common.command_request(f"bench-startup-{next(self._ids)}")
            replies = self.session.get(key, payload=payload, timeout=REPLY_WAIT_S)
            if any(r.ok is not None for r in replies):
                return time.perf_counter() - began
            if proc.poll() is not None:
                raise RuntimeError(f"{key}: the server exited with {proc.returncode}")
            if time.perf_counter() - began > SERVE_TIMEOUT_S:
                raise TimeoutError(f"{key}: nothing served within {SERVE_TIMEOUT_S:g} s")
            time.sleep(POLL_S)

    def close(self) -> None:
        self.session.close()  # type: ignore[no-untyped-call]


LOG_STEPS = {"bus_started": "exec → bus up", "started": "exec → loop running"}
"""The daemon's log events whose time is shown, and the row each gives."""


def _log_steps(log: Path, exec_wall: float) -> dict[str, float]:
    """Seconds from exec to each of `LOG_STEPS` in the daemon's log (its `ts` is UTC)."""
    found: dict[str, float] = {}
    for line in log.read_text().splitlines():
        event = re.search(r"\bevent=(\w+)", line)
        stamp = re.match(r"ts=(\S+)Z", line)
        if event and stamp and event.group(1) in LOG_STEPS and event.group(1) not in found:
            wall = datetime.fromisoformat(stamp.group(1) + "+00:00").timestamp()
            found[event.group(1)] = wall - exec_wall
    return found


class Starts:
    """Cold starts of the daemon and of the bare server, each polled to its first reply."""

    def __init__(self, tmp: Path, listener: Listener) -> None:
        self.tmp = tmp
        self.listener = listener
        self.zconf = write_zenoh_config(tmp)
        self.steps: dict[str, list[float]] = {row: [] for row in LOG_STEPS.values()}
        self._runs = itertools.count()

    def served(self, cmd: list[str], key: str, log: Path) -> float:
        exec_wall = time.time()
        began = time.perf_counter()
        with log.open("w") as out:
            proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, text=True)
        try:
            return self.listener.first_reply(proc, key, began)
        finally:
            stop_process(proc)
            for event, seconds in _log_steps(log, exec_wall).items():
                self.steps[LOG_STEPS[event]].append(seconds)

    def daemon(self) -> float:
        n = next(self._runs)
        cmd = machine_cmd(
            "run",
            "--sim",
            "--id",
            "m1",
            "--zenoh-config",
            str(self.zconf),
            "--listen",
            f"tcp/127.0.0.1:{free_port()}",
            "--connect",
            self.listener.endpoint,
            "--data-dir",
            str(self.tmp / f"data-{n}"),
        )
        return self.served(cmd, CHECK_KEY.format(id="m1"), self.tmp / f"daemon-{n}.log")

    def bare(self) -> float:
        key = CHECK_KEY.format(id="bare")
        cmd = [sys.executable, "-c", BARE_SERVE, str(self.zconf), self.listener.endpoint, key]
        return self.served(cmd, key, self.tmp / "bare.log")


# --------------------------------------------------------------------------------- the run
@dataclass(frozen=True)
class Cli:
    """How to run one `rider`: its command line up to the arguments, where, with what env."""

    argv: list[str]
    cwd: Path = REPO
    env: dict[str, str] | None = None

    def timed(self, *args: str) -> float:
        return timed_run([*self.argv, *args], cwd=self.cwd, env=self.env)


CONSOLE_SCRIPT = "import sys; from ride_machine.rider.cli import main; sys.exit(main())"
"""What the `rider` console script runs, for a tree that is not installed."""


@contextlib.contextmanager
def cli_at(rev: str | None) -> Iterator[Cli | None]:
    """The `rider` of git revision `rev` (its rider/, schema/ and common/ trees, ahead of the
    installed ones on the path), run as the console script runs it; None without `rev`."""
    if rev is None:
        yield None
        return
    with tempfile.TemporaryDirectory(prefix="bench-startup-rev-") as tmp_name:
        tree = Path(tmp_name)
        archive = subprocess.run(
            ["git", "archive", "--format=tar", rev, "rider", "schema", "common"],
            cwd=REPO,
            capture_output=True,
            check=True,
        )
        with tarfile.open(fileobj=io.BytesIO(archive.stdout)) as tar:
            tar.extractall(tree, filter="data")
        env = {**os.environ, "PYTHONPATH": str(tree)}
        yield Cli([sys.executable, "-c", CONSOLE_SCRIPT], cwd=tree, env=env)


def _cli_rounds(runs: int, before: Cli | None, rev: str | None) -> dict[str, common.Dist]:
    rider = Cli(rider_script())
    with bench_daemon() as daemon:
        to_daemon = ["--connect", daemon.endpoint, "--zenoh-config", str(daemon.zenoh_config)]
        status_key = f"machine/{daemon.machine_id}/status"
        bare = [sys.executable, "-c", BARE_READ, str(daemon.zenoh_config), daemon.endpoint]
        variants: dict[str, Callable[[], float]] = {
            "python -c pass (floor)": lambda: timed_run([sys.executable, "-c", "pass"]),
            "rider --help": lambda: rider.timed("--help"),
            "bare Zenoh read, fresh interpreter (floor)": lambda: timed_run([*bare, status_key]),
            "rider -m m1 status": lambda: rider.timed(*to_daemon, "-m", "m1", "status"),
            "rider status (discovery settles)": lambda: rider.timed(*to_daemon, "status"),
        }
        if before is not None:
            variants |= {
                f"rider --help at {rev}": lambda: before.timed("--help"),
                f"rider -m m1 status at {rev}": lambda: before.timed(
                    *to_daemon, "-m", "m1", "status"
                ),
                f"rider status at {rev}": lambda: before.timed(*to_daemon, "status"),
            }
        return interleaved(runs, variants)


def _serve_rounds(runs: int) -> tuple[dict[str, common.Dist], dict[str, common.Dist]]:
    with tempfile.TemporaryDirectory(prefix="bench-startup-") as tmp_name:
        tmp = Path(tmp_name)
        listener = Listener(write_zenoh_config(tmp))
        try:
            starts = Starts(tmp, listener)
            served = interleaved(
                runs,
                {
                    "bare Zenoh queryable, fresh interpreter (floor)": starts.bare,
                    "machine run --sim (cold, fresh data dir)": starts.daemon,
                },
            )
        finally:
            listener.close()
    return served, {row: common.Dist.of(s) for row, s in starts.steps.items()}


def _ms(seconds: float) -> str:
    return ms(seconds, 1)


def _table(title: str, dists: dict[str, common.Dist], note: str) -> common.Table:
    table = common.Table(title, ["what", "n", "p50", "p90", "max"], note=note)
    for name, d in dists.items():
        table.add(name, d.n, _ms(d.p50), _ms(d.p90), _ms(d.max))
    return table


def run(opts: common.Options, rev: str | None = None) -> common.Section:
    """The benchmark; with `rev`, that revision's `rider` too, in the same rounds."""
    runs = opts.pick(3, 20, 50)
    load_cli = load_now()
    with cli_at(rev) as before:
        cli = _cli_rounds(runs, before, rev)
    load_serve = load_now()
    served, steps = _serve_rounds(runs)
    load_end = load_now()
    cli_table = _table(
        "Wall time from exec to exit, ms",
        cli,
        "interleaved round by round; each a fresh process; the daemon a simulator at 10 ms;"
        f" host load average (1 min) {load_cli} before, {load_serve} after",
    )
    serve_table = _table(
        "Exec → first command served, ms",
        {**served, **{f"machine run: {row}": d for row, d in steps.items()}},
        "polled with a CheckHome every 2 ms until one is answered; the daemon's own steps"
        f" from its log's timestamps (same wall clock); host load average (1 min) {load_serve}"
        f" before, {load_end} after",
    )
    daemon = served["machine run --sim (cold, fresh data dir)"]
    return common.Section(
        "startup",
        "Start-up: rider --help, rider status, exec → first command",
        tables=[cli_table, serve_table],
        targets=[
            common.Target.at_most("rider --help, p50", cli["rider --help"].p50, HELP_TARGET_S, _ms),
            common.Target.at_most(
                "loopback rider status, p50",
                cli["rider status (discovery settles)"].p50,
                STATUS_TARGET_S,
                _ms,
            ),
            common.Target.at_most(
                "loopback rider -m m1 status, p50",
                cli["rider -m m1 status"].p50,
                STATUS_TARGET_S,
                _ms,
            ),
            common.Target.at_most(
                "daemon exec → first command served, p50", daemon.p50, SERVED_TARGET_S, _ms
            ),
            common.Target.at_most(
                "daemon exec → first command served, max", daemon.max, SERVED_TARGET_S, _ms
            ),
        ],
        notes=[
            f"`rider status` without `-m` waits for discovery to settle ({SETTLE_S * 1e3:.0f}"
            " ms without a new token or link, rider/discovery.py) before it may call a machine"
            " the only one; the CLI starts that lookup as soon as its session is open, so the"
            " window runs while it loads the client and the wire models. `-m m1` names the"
            " machine and looks up nothing.",
        ],
    )


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    parser = common.build_parser("bench.startup", __doc__.splitlines()[0])
    parser.add_argument(
        "--against", metavar="REV", help="also time the rider of this git revision (a baseline)"
    )
    args = parser.parse_args(argv)
    opts = common.options_from(args)
    with common.interrupts_as_exceptions():
        common.save(
            common.measure(
                lambda o: run(o, args.against), opts, common.command_line("bench.startup", argv)
            ),
            opts,
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
