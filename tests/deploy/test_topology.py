"""compose.yaml replayed in network namespaces: the two containers without a container engine.

The `machine` service runs in one namespace, the `rider` service (the operator UI) in another,
joined by a veth pair; each namespace has a hosts file that makes the compose service names
resolve, as the compose network's DNS does. The commands are compose.yaml's own, read from the
parsed file: only container paths become host paths (by the service's mounts), and the mounted
machine.toml is swapped for a fast simulator config (a site mounts its own config there too).
`docker compose exec rider rider …` is the Rider CLI in the rider namespace with that service's
environment. The machine service runs as compose.yaml has it: the daemon under its supervisor.
(The router of docker/compose.router.yaml is run by tests/deploy/test_router.py.)

Skipped, with the reason, where namespaces cannot be created (not root, no iproute2).
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

from ride_machine.rider.cli import EXIT_OK
from ride_machine.schema.commands import RotateStep, Session
from ride_machine.schema.status import MachineState, Status
from ride_machine.service.adapters.credentials import identities, init_credentials
from tests.deploy import spec
from tests.freeze_whole import plant_world
from tests.integration.support import write_fast_config
from tests.netns import NetnsUnavailable, NsPair, hosts_file, unavailable_reason, veth_pair
from tests.procs import REPO, child_pids

pytestmark = [
    pytest.mark.integration,
    pytest.mark.netns,
    pytest.mark.skipif(unavailable_reason() is not None, reason=str(unavailable_reason())),
]

READY_TIMEOUT_S = 30.0
"""Bound for a service to start (the daemon's bus up, the UI listening)."""
STEP_TIMEOUT_S = 60.0
"""Bound for one Rider CLI process (a calibration, homing or a whole session at fast speed)."""
STOP_TIMEOUT_S = 15.0

ALL_STATES = [s.value for s in MachineState]
HEARTBEAT = "/dev/shm/machine.heartbeat"


@dataclass
class Child:
    """A service's process; a thread drains its output so a test can wait for a line."""

    name: str
    proc: subprocess.Popen[str]
    lines: list[str] = field(default_factory=list)
    ended: bool = False
    cond: threading.Condition = field(default_factory=threading.Condition)

    @classmethod
    def start(cls, name: str, argv: list[str], env: dict[str, str]) -> Child:
        proc = subprocess.Popen(
            argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=REPO, env=env
        )
        child = cls(name, proc)
        threading.Thread(target=child._drain, name=f"drain-{name}", daemon=True).start()
        return child

    def _drain(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            with self.cond:
                self.lines.append(line.rstrip("\n"))
                self.cond.notify_all()
        with self.cond:
            self.ended = True
            self.cond.notify_all()

    def wait_line(self, text: str, timeout: float = READY_TIMEOUT_S) -> str:
        """The first output line containing `text`; fails when the process ends or time's up."""
        deadline = time.monotonic() + timeout
        with self.cond:
            while True:
                found = next((line for line in self.lines if text in line), None)
                if found is not None:
                    return found
                left = deadline - time.monotonic()
                if self.ended or left <= 0:
                    raise AssertionError(f"{self.name}: no line with {text!r}:\n{self.log()}")
                self.cond.wait(left)

    def log(self) -> str:
        return "\n".join(self.lines)

    def stop(self, timeout: float = STOP_TIMEOUT_S) -> int:
        """SIGTERM, as `docker compose stop` sends; SIGKILL only if it overstays `timeout`."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(STOP_TIMEOUT_S)
        return self.proc.returncode


@dataclass
class Stack:
    """compose.yaml's services placed in the two namespaces of `net`."""

    net: NsPair
    tmp: Path
    compose: dict[str, Any]
    children: dict[str, Child] = field(default_factory=dict)
    config_extra: str = ""
    """Appended to the fast config that replaces the mounted machine.toml."""

    def ns(self, name: str) -> str:
        return self.net.a if name in ("machine", "plant") else self.net.b

    def svc(self, name: str) -> dict[str, Any]:
        return spec.service(self.compose, name)

    def paths(self, name: str) -> dict[str, Path]:
        fast = write_fast_config(self.tmp)
        fast.write_text(fast.read_text() + self.config_extra)
        return spec.mount_paths(self.svc(name), self.tmp / "volumes", {"./machine.toml": fast})

    def secrets(self, name: str) -> dict[str, Path]:
        """The service's /run/secrets files, made here as `machine credentials init` makes them."""
        host_dir = self.tmp / "secrets"
        if not host_dir.exists():
            init_credentials(host_dir, identities())
        return spec.secret_paths(self.compose, self.svc(name), host_dir)

    def env(self, name: str) -> dict[str, str]:
        svc_env = spec.environment(self.svc(name))
        paths = {**self.secrets(name), **self.tmpfs()}
        svc_env = {k: str(paths.get(v, v)) for k, v in svc_env.items()}
        return {**os.environ, "PYTHONUNBUFFERED": "1", **svc_env}

    def tmpfs(self) -> dict[str, Path]:
        """The container's /dev/shm (the heartbeat file) as a directory of this test."""
        shm = self.tmp / "shm"
        shm.mkdir(exist_ok=True)
        return {HEARTBEAT: shm / Path(HEARTBEAT).name}

    def up(self, name: str) -> Child:
        argv = spec.command(self.svc(name))
        host = spec.host_argv(argv, self.paths(name))
        child = Child.start(name, self.net.cmd(self.ns(name), host), self.env(name))
        self.children[name] = child
        return child

    def run(self, name: str, argv: list[str]) -> subprocess.CompletedProcess[str]:
        """A command in service `name`'s namespace, with its environment (compose exec)."""
        return subprocess.run(
            self.net.cmd(self.ns(name), spec.host_argv(argv, self.paths(name))),
            capture_output=True,
            text=True,
            timeout=STEP_TIMEOUT_S,
            cwd=REPO,
            env=self.env(name),
            check=False,
        )

    def rider(self, *args: str) -> subprocess.CompletedProcess[str]:
        """`docker compose exec rider rider ARGS`; exit 0 required."""
        done = self.run("rider", ["rider", *args])
        assert done.returncode == EXIT_OK, self.explain(args, done)
        return done

    def healthcheck(self, name: str, argv: list[str] | None = None) -> int:
        """The service's healthcheck (CMD-SHELL: `sh -c STRING`) in its namespace, container
        paths and `python` made this host's."""
        argv = argv or spec.healthcheck_argv(self.svc(name))
        script = argv[-1].replace(HEARTBEAT, str(self.tmpfs()[HEARTBEAT]))
        script = script.replace("python -c", f"{sys.executable} -c")
        done = subprocess.run(
            self.net.cmd(self.ns(name), [*argv[:-1], script]),
            capture_output=True, text=True, timeout=STEP_TIMEOUT_S, env=self.env(name),
            check=False,
        )  # fmt: skip
        return done.returncode

    def explain(self, what: object, done: subprocess.CompletedProcess[str]) -> str:
        logs = "\n".join(f"--- {n}\n{c.log()}" for n, c in self.children.items())
        return f"{what}: exit {done.returncode}\n{done.stdout}\n{done.stderr}\n{logs}"

    def close(self) -> None:
        for child in reversed(self.children.values()):
            child.stop()


def image_healthcheck() -> list[str]:
    (check,) = [i.args for i in spec.image(spec.dockerfile()) if i.keyword == "HEALTHCHECK"]
    return spec.exec_form(spec.split_options(check)[1].removeprefix("CMD "))


def last_status(output: str) -> Status:
    return Status.model_validate_json(output.strip().splitlines()[-1])


@pytest.fixture
def stack(tmp_path: Path) -> Iterator[Stack]:
    try:
        with contextlib.ExitStack() as stack:
            net = stack.enter_context(veth_pair("zd"))
            # The compose network's DNS: every service name, from every container.
            names = {"machine": net.addr_a, "rider": net.addr_b}
            for ns in (net.a, net.b):
                stack.enter_context(hosts_file(ns, names))
            site = Stack(net, tmp_path, spec.load_compose())
            stack.callback(site.close)
            yield site
    except NetnsUnavailable as exc:
        pytest.skip(f"cannot create network namespaces here: {exc}")


def test_compose_stack_runs_a_session_to_done_and_stops_safely(stack: Stack) -> None:
    machine = stack.up("machine")
    machine.wait_line("event=started")
    ui = stack.up("rider")
    ui.wait_line("rider ui: http://")

    # Docker's view: the daemon's loop cycles in its own container, the UI answers in its own.
    deadline = time.monotonic() + READY_TIMEOUT_S
    while stack.healthcheck("machine") != EXIT_OK:  # the first touch comes about 1 s in
        assert time.monotonic() < deadline, machine.log()
        time.sleep(0.25)
    assert stack.healthcheck("machine", image_healthcheck()) == EXIT_OK
    assert stack.healthcheck("rider") == EXIT_OK, ui.log()

    # An operator at the rider container: a whole session over tcp/machine:7447.
    stack.rider("calibrate", "tilt", "--wait")
    stack.rider("calibrate", "rotate", "--wait")
    stack.rider("home", "--wait")
    done = last_status(stack.rider("--json", "start", "--wait").stdout)
    assert done.state is MachineState.DONE
    status = last_status(stack.rider("--json", "status").stdout)
    assert status.state is MachineState.DONE and status.machine_id == "m1"
    assert status.session is not None and status.session.revolutions_done == 3

    # The UI, fed over the same veth, shows the session's end too.
    port = str(spec.parse_cli(spec.command(stack.svc("rider"))).ui.port)
    probe = stack.run(
        "rider",
        ["python", "-m", "tests.deploy.ui_probe", f"http://127.0.0.1:{port}", "DONE"],
    )
    assert probe.returncode == 0, stack.explain("ui_probe", probe)

    # `docker compose stop` in the middle of a ride: SIGTERM, outputs safe, exit 0 in time.
    # A ride long enough that a watcher started after it, on a loaded host, still finds it
    # RUNNING (the default session, 3 revolutions at the fast config, had ended: run 48).
    long_ride = stack.tmp / "long-ride.json"
    long_ride.write_text(
        Session(name="long", steps=[RotateStep(revolutions=100)]).model_dump_json()
    )
    stack.rider("home", "--wait")
    stack.rider("start", "--session", str(long_ride))
    stack.rider("watch", "--keys", "status", "--until", "RUNNING", "--for", "30")
    grace = spec.seconds(stack.svc("machine")["stop_grace_period"])
    machine.proc.send_signal(signal.SIGTERM)
    try:
        code = machine.proc.wait(grace)
    except subprocess.TimeoutExpired:
        raise AssertionError(f"still running after {grace:g} s: docker would SIGKILL it") from None
    assert code == 0, machine.log()
    machine.wait_line("event=signal signal=SIGTERM")
    machine.wait_line("event=stopped code=0 outputs=safe")
    assert stack.healthcheck("machine") != EXIT_OK  # the stopped daemon removed its file
    assert ui.stop(grace) == 0, ui.log()


PUMP = '\n[hal.iomap]\nchargePump = "O_5"\n'


def test_the_plant_in_a_container_of_its_own_cuts_the_drives_when_the_machine_is_paused(
    stack: Stack,
) -> None:
    """docker/compose.plant.yaml (issue 53): the simulated plant a service of its own, the
    machine's supervisor attached to it through the shared volume. `docker compose pause
    machine` (every process of the machine's container stopped; here SIGSTOP of its process
    tree) leaves the plant running, and its charge-pump relay cuts the drives."""
    stack.compose = spec.merged(stack.compose, spec.load_compose(spec.PLANT_OVERRIDE))
    stack.config_extra = PUMP
    plant = stack.up("plant")
    plant.wait_line("event=plant_started")
    machine = stack.up("machine")
    machine.wait_line("event=started")
    machine.wait_line("event=plant_found")
    stack.rider("calibrate", "tilt", "--wait")
    stack.rider("calibrate", "rotate", "--wait")
    stack.rider("home", "--wait")
    long_ride = stack.tmp / "long-ride.json"
    long_ride.write_text(
        Session(name="long", steps=[RotateStep(revolutions=100)]).model_dump_json()
    )
    stack.rider("start", "--session", str(long_ride))
    stack.rider("watch", "--keys", "status", "--until", "RUNNING", "--for", "30")
    volume = stack.tmp / "volumes" / "plant"
    tree = [machine.proc.pid, *descendants(machine.proc.pid)]
    for pid in tree:
        os.kill(pid, signal.SIGSTOP)
    try:
        t0 = time.monotonic()
        while (left := t0 + 1.0 - time.monotonic()) > 0:
            time.sleep(left)  # the pause itself
        world = plant_world(volume)
    finally:
        for pid in tree:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGCONT)
    assert plant.proc.poll() is None, plant.log()
    assert world.drives_powered is False and world.drives_off_s is not None, world
    assert world.clock is not None
    cut = world.clock - world.drives_off_s - t0
    assert cut <= 0.3, f"drives cut {cut:.3f} s after the pause"
    assert any(world.relays.values()), "the paused machine's relays stay as they were"


def descendants(pid: int) -> list[int]:
    """Every process below `pid` (the container's other processes)."""
    out = []
    for child in child_pids(pid):
        out += [child, *descendants(child)]
    return out
