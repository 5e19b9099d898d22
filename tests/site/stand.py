"""A site on loopback for tests: a router process, daemons that join it, Riders through it.

Configs come from docs/site.md (its `<!-- site-config: NAME -->` json5 blocks) and from the
shipped zenoh.json5, so the documentation is what the tests run. Every process is bounded and
killed at the end, even when a test fails.
"""

from __future__ import annotations

import contextlib
import os
import queue
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from ride_machine.rider.client import Rider
from tests.integration.support import fast_args
from tests.procs import REPO, START_TIMEOUT_S, Daemon, free_port, start_daemon, stop_process

DOC = REPO / "docs" / "site.md"
PEER_CONFIG = REPO / "zenoh.json5"
FOLLOW_S = 10.0
"""How long `Site.wait_alive` follows tokens before it asks for them instead."""
Mode = Literal["client", "peer"]


def doc_config(name: str) -> str:
    """The json5 block that follows `<!-- site-config: NAME -->` in docs/site.md."""
    pattern = rf"<!-- site-config: {re.escape(name)} -->\s*```json5\n(.*?)```"
    found = re.search(pattern, DOC.read_text(), re.S)
    if found is None:
        raise LookupError(f"docs/site.md has no site-config block {name!r}")
    return found.group(1)


def write_doc_config(directory: Path, name: str) -> Path:
    path = directory / f"site-{name}.json5"
    path.write_text(doc_config(name))
    return path


class Lines:
    """A child's stdout, line by line, read by a thread so every wait can be bounded."""

    def __init__(self, proc: subprocess.Popen[str]) -> None:
        self.proc = proc
        self._q: queue.Queue[tuple[float, str] | None] = queue.Queue()
        self.seen: list[str] = []
        threading.Thread(target=self._pump, daemon=True).start()

    def _pump(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self._q.put((time.monotonic(), line.rstrip("\n")))
        self._q.put(None)

    def wait_for(self, wanted: str, timeout: float = START_TIMEOUT_S) -> tuple[float, str]:
        """The first new line containing `wanted`, and when it was read."""
        deadline = time.monotonic() + timeout
        while True:
            try:
                item = self._q.get(timeout=max(0.0, deadline - time.monotonic()))
            except queue.Empty:
                raise AssertionError(f"no {wanted!r} in {timeout:g} s: {self.seen}") from None
            if item is None:
                raise AssertionError(f"output ended before {wanted!r}: {self.seen}")
            self.seen.append(item[1])
            if wanted in item[1]:
                return item

    def rest(self, timeout: float = START_TIMEOUT_S) -> list[str]:
        """The lines not read yet, once the child has closed its output."""
        out: list[str] = []
        deadline = time.monotonic() + timeout
        while (item := self._q.get(timeout=max(0.0, deadline - time.monotonic()))) is not None:
            out.append(item[1])
        return out


@dataclass
class Router:
    """The router process (tests/site/router.py) on a fixed loopback port, restartable."""

    config: Path
    log_dir: Path
    port: int = field(default_factory=free_port)
    connect: list[str] = field(default_factory=list)
    """Endpoints the router dials itself (a router that connects to a machine)."""
    proc: subprocess.Popen[str] | None = None
    starts: int = 0

    @property
    def endpoint(self) -> str:
        return f"tcp/127.0.0.1:{self.port}"

    def start(self) -> None:
        """Start on the same port every time; return once it listens."""
        self.starts += 1
        log = (self.log_dir / f"router-{self.starts}.log").open("w")
        self.proc = subprocess.Popen(
            [
                *[sys.executable, "-m", "tests.site.router", "--config", str(self.config)],
                *["--listen", self.endpoint],
                *[arg for endpoint in self.connect for arg in ("--connect", endpoint)],
            ],
            stdout=subprocess.PIPE,
            stderr=log,
            text=True,
            cwd=REPO,
        )
        log.close()
        try:
            Lines(self.proc).wait_for('"ready"')
        except BaseException:
            self.kill()
            raise

    def kill(self, sig: int = signal.SIGKILL) -> None:
        if self.proc is not None:
            stop_process(self.proc, sig)


@dataclass
class Site:
    """One router plus the daemons that joined it; Riders connect only to the router."""

    tmp: Path
    router: Router
    client_config: Path
    daemons: dict[str, Daemon] = field(default_factory=dict)

    def start_daemons(self, modes: dict[str, Mode], *more: str) -> list[Daemon]:
        """Start one daemon per id (client or peer mode), all at once; wait until all are alive."""
        started = [self.add_daemon(mid, mode, *more) for mid, mode in modes.items()]
        self.wait_alive(modes)
        return started

    def add_daemon(self, machine_id: str, mode: Mode, *more: str) -> Daemon:
        """`machine run` joining the router; a peer also listens on its own loopback port."""
        zconf = PEER_CONFIG if mode == "peer" else self.client_config
        extra = [*fast_args(self.tmp), "--zenoh-config", str(zconf)]
        extra += ["--connect", self.router.endpoint, *more]
        daemon = start_daemon(self.tmp, machine_id, extra=extra, wait=False)
        self.daemons[machine_id] = daemon
        return daemon

    def rider(self, machine_id: str | None, mode: Mode = "client", **kwargs: Any) -> Rider:
        """A Rider that connects only to the router."""
        zconf = PEER_CONFIG if mode == "peer" else self.client_config
        return Rider(
            machine_id,
            connect=[self.router.endpoint],
            zenoh_config_path=zconf,
            **kwargs,
        )

    def wait_alive(self, ids: Iterable[str], timeout: float = START_TIMEOUT_S) -> None:
        """Until every id's liveliness token is seen through the router and it answers: first
        as it comes (a follower), then, for any still missing after `FOLLOW_S`, by asking for
        the tokens alive. Once in a full CI run a follower was given no new token for 20 s
        while the machine served (zenoh 1.10, a client behind a router); a listing asks the
        router what it holds instead."""
        ids, deadline = list(ids), time.monotonic() + timeout
        with self.rider(None, timeout=1.0) as r:
            wanted = dict.fromkeys(ids, True)
            try:
                wait_tokens(r.follow_machines(timeout=0.2), wanted, FOLLOW_S, self.daemons)
                missing: list[str] = []
            except TokensLate as late:
                missing = late.missing
        while missing:
            with self.rider(None, timeout=1.0) as r:
                listed = {m.id for m in r.machines(with_status=False)}
            missing = [mid for mid in missing if mid not in listed]
            if missing and time.monotonic() > deadline:
                raise AssertionError(f"liveliness: {missing} never seen through the router")
        for mid in ids:
            with self.rider(mid, timeout=5.0) as one:
                assert one.status().machine_id == mid  # the token comes with the first status

    def rider_cmd(self, *args: str) -> list[str]:
        return [
            *[sys.executable, "-m", "ride_machine.rider.cli", "--connect", self.router.endpoint],
            *["--zenoh-config", str(self.client_config), *args],
        ]

    def close(self) -> None:
        """Stop every daemon (SIGTERM, then SIGKILL past the bound) and kill the router."""
        for daemon in self.daemons.values():
            with contextlib.suppress(ProcessLookupError):
                daemon.proc.send_signal(signal.SIGCONT)  # a frozen one must be able to stop
            daemon.stop()
        self.router.kill(signal.SIGTERM)


def wait_tokens(
    changes: Iterator[tuple[str, bool] | None],
    wanted: dict[str, bool],
    timeout: float,
    daemons: dict[str, Daemon] | None = None,
) -> dict[str, float]:
    """Read `Rider.follow_machines` changes until each id reached its wanted state (True alive,
    False gone); returns when each got there (monotonic). Fails early if a daemon exits."""
    todo = dict(wanted)
    current: dict[str, bool] = {}
    reached: dict[str, float] = {}
    deadline = time.monotonic() + timeout
    for change in changes:
        if change is not None:
            mid, alive = change
            current[mid] = alive
            if todo.get(mid) is alive:
                reached[mid] = time.monotonic()
                del todo[mid]
        if not todo:
            return reached
        for mid, alive in todo.items():
            daemon = (daemons or {}).get(mid)
            if daemon is not None and alive and daemon.proc.poll() is not None:
                raise AssertionError(f"daemon {mid} exited:\n{daemon.log()}")
        if time.monotonic() > deadline:
            raise TokensLate(f"liveliness: still waiting for {todo} (seen {current})", list(todo))
    raise AssertionError("unreachable")


class TokensLate(AssertionError):
    """`wait_tokens` ran out of time; `missing`: the ids that had not reached their state."""

    def __init__(self, message: str, missing: list[str]) -> None:
        super().__init__(message)
        self.missing = missing


@contextlib.contextmanager
def linked_peers(tmp: Path) -> Iterator[tuple[Daemon, Daemon]]:
    """Two peer daemons on the shipped zenoh.json5 and no router, `fb` started with `--connect`
    to `fa` (issue 22's case); both stopped after, `fb` first."""
    zconf = ["--zenoh-config", str(PEER_CONFIG)]
    fa = start_daemon(tmp, "fa", extra=zconf)
    try:
        fb = start_daemon(tmp, "fb", extra=[*zconf, "--connect", fa.endpoint])
        try:
            yield fa, fb
        finally:
            fb.stop()
    finally:
        fa.stop()


@contextlib.contextmanager
def site(tmp: Path) -> Iterator[Site]:
    """A running router and an empty site; everything is torn down on exit."""
    router = Router(write_doc_config(tmp, "router"), tmp)
    stand = Site(tmp, router, write_doc_config(tmp, "client"))
    try:
        router.start()
        yield stand
    finally:
        stand.close()


def run_cli(cmd: Sequence[str], timeout: float = 30.0) -> subprocess.CompletedProcess[str]:
    """One bounded `rider` process."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    return subprocess.run(
        cmd, capture_output=True, text=True, timeout=timeout, cwd=REPO, env=env, check=False
    )
