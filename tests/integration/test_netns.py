"""The machine and the Rider in two network namespaces joined by a veth pair.

This is the topology of a machine container and a rider container on one compose network:
the daemon listens only on its own namespace's address, the Rider reaches it across the veth.
Skipped, with the reason, where the test cannot create namespaces.
"""

from __future__ import annotations

import json
import subprocess
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from ride_machine.rider.client import MachineTimeout, Rider
from ride_machine.schema.status import MachineState, Status
from tests.integration import rider_proc
from tests.integration.support import STEP_TIMEOUT_S, fast_args
from tests.netns import NetnsUnavailable, NsPair, unavailable_reason, veth_pair
from tests.procs import REPO, Daemon, rider_cmd, run_bounded, start_daemon

pytestmark = [
    pytest.mark.integration,
    pytest.mark.netns,
    pytest.mark.skipif(unavailable_reason() is not None, reason=str(unavailable_reason())),
]

RUN_TIMEOUT_S = 60.0
"""Bound for one Rider process that drives a whole session (prepare + run)."""


@dataclass
class Site:
    """A daemon in namespace `a`; Riders are run in namespace `b`."""

    net: NsPair
    daemon: Daemon

    def in_b(self, *args: str) -> list[str]:
        return self.net.cmd(self.net.b, args)

    def in_a(self, *args: str) -> list[str]:
        return self.net.cmd(self.net.a, args)

    def rider_proc(self, *steps: str) -> list[str]:
        d = self.daemon
        return rider_proc.command(d.endpoint, d.zenoh_config, d.machine_id, *steps)

    def rider_cli(self, *args: str) -> list[str]:
        endpoint, zconf = self.daemon.endpoint, str(self.daemon.zenoh_config)
        return rider_cmd("--connect", endpoint, "--zenoh-config", zconf, *args)


@pytest.fixture
def site(tmp_path: Path) -> Iterator[Site]:
    try:
        with veth_pair() as net:
            daemon = start_daemon(
                tmp_path,
                netns=net.a,
                listen_host=net.addr_a,
                extra=fast_args(tmp_path),
                wait=False,  # this process cannot reach namespace a; the Rider in b waits
            )
            try:
                yield Site(net, daemon)
            finally:
                daemon.stop()
    except NetnsUnavailable as exc:
        pytest.skip(f"cannot create network namespaces here: {exc}")


def reports(output: str) -> dict[str, dict[str, Any]]:
    records = [json.loads(line) for line in output.splitlines() if line.startswith("{")]
    errors = [r["error"] for r in records if "error" in r]
    assert not errors, errors
    return {r["step"]: r for r in records}


def test_a_session_runs_across_two_namespaces(site: Site) -> None:
    run = run_bounded(
        site.in_b(*site.rider_proc("alive", "prepare", "start", "done")), RUN_TIMEOUT_S
    )
    assert run.returncode == 0, f"{run.stdout}\n{run.stderr}\n{site.daemon.log()}"
    steps = reports(run.stdout)
    done = Status.model_validate(steps["done"]["status"])
    assert done.state is MachineState.DONE
    assert done.session is not None and done.session.revolutions_done == 3
    assert steps["done"]["revolutions"] == pytest.approx(3.0, abs=0.1)

    cli = run_bounded(site.in_b(*site.rider_cli("--json", "status")), RUN_TIMEOUT_S)
    assert cli.returncode == 0, cli.stderr
    assert Status.model_validate_json(cli.stdout).state is MachineState.DONE

    # The host's namespace has no route to the machine: the session really crossed the veth.
    with (
        Rider("m1", connect=[site.daemon.endpoint], timeout=0.5) as outsider,
        pytest.raises(MachineTimeout),
    ):
        outsider.status()


def start_driver(site: Site) -> subprocess.Popen[str]:
    """A Rider in namespace b on Zenoh's default lease (its --zenoh-config dropped) riding a
    long session."""
    d = site.daemon
    steps = ("--revolutions", "40", "alive", "prepare", "start", "running", "hold")
    driver_cmd = [*rider_proc.command(d.endpoint, d.zenoh_config, d.machine_id, *steps)]
    at = driver_cmd.index("--zenoh-config")
    del driver_cmd[at : at + 2]
    return subprocess.Popen(
        site.in_b(*driver_cmd),
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        cwd=REPO,
    )


def wait_holding(site: Site, driver: subprocess.Popen[str]) -> None:
    """Until the driver reports its `hold` step (the session running); every step error-free."""
    assert driver.stdout is not None
    for line in driver.stdout:
        record = json.loads(line)
        assert "error" not in record, record
        if record["step"] == "hold":
            break
    else:
        raise AssertionError(f"driver ended early:\n{site.daemon.log()}")


@pytest.mark.hazard("H06", "H36")
def test_a_pulled_cable_pauses_the_session_by_the_riders_heartbeat(site: Site) -> None:
    """No FIN, no RST, and a Rider on Zenoh's default 10 s lease (no --zenoh-config): only its
    deadman heartbeat (`rider_loss.timeout_s`, 1 s in the fast test config) can notice."""
    driver = start_driver(site)
    watcher: subprocess.Popen[str] | None = None
    try:
        wait_holding(site, driver)
        # A watcher beside the machine, in namespace a, sees what the pulled cable does.
        watcher = subprocess.Popen(
            site.in_a(
                *site.rider_cli(
                    "--json", "watch", "--keys", "status", "--for", "20", "--until", "PAUSED"
                )
            ),
            stdout=subprocess.PIPE,
            text=True,
            cwd=REPO,
        )
        assert watcher.stdout is not None
        first = Status.model_validate_json(watcher.stdout.readline())
        assert first.state is MachineState.RUNNING
        cut_at = time.monotonic()
        site.net.link(site.net.b, up=False)
        paused: Status | None = None
        for line in watcher.stdout:
            status = Status.model_validate_json(line)
            if status.state is MachineState.PAUSED:
                paused = status
                break
        noticed_s = time.monotonic() - cut_at
        assert watcher.wait(STEP_TIMEOUT_S) == 0
        print(f"pulled cable: link down -> PAUSED seen beside the machine in {noticed_s:.2f} s")
        assert paused is not None, site.daemon.log()
        assert any("Rider lost" in w for w in paused.warnings), paused.warnings
        assert site.daemon.has_logged("cause=heartbeat")  # not the 10 s lease
        world = subprocess.run(
            site.in_a(*site.rider_cli("--json", "sim", "world")),
            capture_output=True,
            text=True,
            timeout=STEP_TIMEOUT_S,
            cwd=REPO,
            check=True,
        )
        assert not any(json.loads(world.stdout)["relays"].values())
    finally:
        for proc in (driver, watcher):
            if proc is not None:
                if proc.poll() is None:
                    proc.kill()
                proc.wait(STEP_TIMEOUT_S)
