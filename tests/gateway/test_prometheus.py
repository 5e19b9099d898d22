"""The gateway's metrics against Debian's Prometheus: `promtool check metrics` on a scrape, the
example alert rules through `promtool check rules` and `promtool test rules`, and a real server
that scrapes the gateway and answers a PromQL query with each machine's state (skipped, with the
reason, where the `prometheus` package is not installed: `make test` installs it as root)."""

from __future__ import annotations

import json
import re
import shutil
import signal
import subprocess
import urllib.parse
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import pytest

from ride_machine.schema.status import MachineState
from tests.gateway.support import GatewayProc, joined, until
from tests.procs import REPO, free_port, stop_process
from tests.site.stand import Site

pytestmark = pytest.mark.integration
RULES = REPO / "docs" / "plant-alerts.yml"
RULE_TESTS = Path(__file__).resolve().parent / "alerts_test.yml"


def tool(name: str) -> str:
    path = shutil.which(name)
    if path is None:
        pytest.skip(f"{name} not installed (Debian's prometheus package; `make prometheus`)")
    return path


def test_promtool_finds_the_exposition_clean(gateway: GatewayProc) -> None:
    promtool = tool("promtool")
    scrape = until("m1's state in a scrape", lambda: _with_state(gateway.scrape()))
    done = subprocess.run(
        [promtool, "check", "metrics"],
        input=scrape,
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert done.returncode == 0 and not done.stdout.strip(), done.stdout + done.stderr
    for name in (
        "ride_machine_alive",
        "ride_machine_state",
        "ride_machine_cycle_execution_seconds",
        "ride_machine_cycle_jitter_seconds",
        "ride_machine_build_info",
        "ride_machine_overruns_total",
        "ride_machine_rider_connected",
        "ride_machine_events_written_total",
        "ride_machine_storage_warnings",
        "ride_machine_uptime_seconds",
    ):
        assert f'\n{name}{{machine="m1"' in scrape, name
    assert 'ride_machine_cycle_execution_seconds{machine="m1",quantile="0.99"}' in scrape
    assert "\nride_gateway_build_info{version=" in scrape


def test_the_example_alert_rules_pass_promtool() -> None:
    promtool = tool("promtool")
    for args in (["check", "rules", str(RULES)], ["test", "rules", str(RULE_TESTS)]):
        done = subprocess.run(
            [promtool, *args],
            capture_output=True,
            text=True,
            timeout=60,
            cwd=RULE_TESTS.parent,
            check=False,
        )
        assert done.returncode == 0, done.stdout + done.stderr
        assert "SUCCESS" in done.stdout


@pytest.fixture
def prometheus(gateway: GatewayProc, tmp_path: Path) -> Iterator[str]:
    """Debian's Prometheus server scraping the gateway every 250 ms; its HTTP API's base URL."""
    server = tool("prometheus")
    port = free_port()
    config = tmp_path / "prometheus.yml"
    config.write_text(
        "global:\n  scrape_interval: 250ms\n  evaluation_interval: 250ms\n"
        "scrape_configs:\n  - job_name: ride-gateway\n"
        f"    static_configs:\n      - targets: ['127.0.0.1:{gateway.metrics_port}']\n"
    )
    proc = subprocess.Popen(
        [
            server,
            f"--config.file={config}",
            f"--storage.tsdb.path={tmp_path / 'tsdb'}",
            f"--web.listen-address=127.0.0.1:{port}",
        ],
        stdout=subprocess.DEVNULL,
        stderr=(tmp_path / "prometheus.log").open("w"),
    )
    base = f"http://127.0.0.1:{port}"
    try:
        until("prometheus ready", lambda: _get(f"{base}/-/ready") is not None or None)
        yield base
    finally:
        stop_process(proc)


def test_prometheus_scrapes_the_gateway_and_promql_returns_each_machines_state(
    plant: Site, prometheus: str
) -> None:
    query = urllib.parse.quote("ride_machine_state == 1")

    def states() -> dict[str, str] | None:
        body = _get(f"{prometheus}/api/v1/query?query={query}")
        if body is None:
            return None
        result = json.loads(body)["data"]["result"]
        return {r["metric"]["machine"]: r["metric"]["state"] for r in result} or None

    def agrees() -> dict[str, str] | None:
        got = states()
        with plant.rider("m1", timeout=5.0, supervise=False) as r:
            now = r.status().state
        return got if got is not None and got.get("m1") == now.value else None

    seen = until("PromQL answers m1's state as the machine does", agrees, timeout=30)
    assert set(seen.values()) <= {s.value for s in MachineState}
    up = _get(f"{prometheus}/api/v1/query?query=up")
    assert up is not None and json.loads(up)["data"]["result"][0]["value"][1] == "1"


def _with_state(scrape: str) -> str | None:
    return scrape if 'ride_machine_state{machine="m1"' in scrape else None


def _get(url: str) -> str | None:
    try:
        with urllib.request.urlopen(url, timeout=5) as r:
            return str(r.read().decode())
    except OSError:
        return None


def test_head_is_answered_as_get_without_a_body(gateway: GatewayProc) -> None:
    request = urllib.request.Request(gateway.metrics_url, method="HEAD")
    with urllib.request.urlopen(request, timeout=5) as r:  # 405 before: an error here
        assert r.status == 200 and r.headers["Content-Type"].startswith("text/plain")
        assert int(r.headers["Content-Length"]) > 0 and r.read() == b""


def _value(scrape: str, name: str, **labels: str) -> float | None:
    """The sample `name{labels}`, or None (prometheus_client writes the labels sorted)."""
    inner = ",".join(f'{k}="{v}"' for k, v in sorted(labels.items()))
    found = re.search(rf"^{name}{{{re.escape(inner)}}} (\S+)$", scrape, re.M)
    return float(found.group(1)) if found else None


@pytest.mark.hazard("H55")
def test_a_machines_command_counters_are_there_at_zero_from_its_first_sight(
    plant: Site, gateway: GatewayProc
) -> None:
    done = {"machine": "counted", "code": "RESP_DONE"}
    with joined(plant, "counted"):
        until(
            "counted in a scrape",
            lambda: _value(gateway.scrape(), "ride_machine_alive", machine="counted") or None,
        )
        # Before its first command: 0, so increase() counts the first one.
        assert _value(gateway.scrape(), "ride_machine_commands_total", **done) == 0.0
        refused = {"machine": "counted", "code": "WRONG_STATE"}
        assert _value(gateway.scrape(), "ride_machine_commands_total", **refused) == 0.0
        with plant.rider("counted", timeout=5.0, supervise=False) as r:
            r.stop()
        until(
            "the Stop counted",
            lambda: _value(gateway.scrape(), "ride_machine_commands_total", **done) == 1.0 or None,
        )


@pytest.mark.hazard("H55")
def test_a_gone_machine_keeps_only_alive_0_so_its_estop_alert_stops(
    plant: Site, gateway: GatewayProc
) -> None:
    def scrape_with(what: str) -> str | None:
        text = gateway.scrape()
        return text if what in text else None

    with joined(plant, "faded") as daemon:
        with plant.rider("faded", timeout=5.0, supervise=False) as r:
            r.sim("estop", pressed=True)
        pressed = 'ride_machine_estop_active{machine="faded"} 1.0'
        until("the E-stop in a scrape", lambda: scrape_with(pressed))
        daemon.proc.send_signal(signal.SIGSTOP)  # frozen past its lease: its token goes
        gone = until("faded gone", lambda: scrape_with('ride_machine_alive{machine="faded"} 0.0'))
        # What RideMachineEstop and RideMachineFault match is gone (stale to Prometheus): only
        # RideMachineGone fires. The time it was last heard stays.
        for name in ("estop_active", "estop_latched", "state", "fault", "uptime_seconds"):
            assert f'ride_machine_{name}{{machine="faded"' not in gone, name
        assert 'ride_machine_cycle_execution_seconds{machine="faded"' not in gone
        assert 'ride_machine_status_timestamp_seconds{machine="faded"}' in gone
        daemon.proc.send_signal(signal.SIGCONT)
        until(
            "faded back, E-stop still latched",
            lambda: scrape_with('ride_machine_estop_latched{machine="faded"} 1.0'),
        )
