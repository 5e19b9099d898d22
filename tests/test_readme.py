"""The README's examples run against a real daemon, so the documentation cannot drift."""

from __future__ import annotations

import os
import re
import shlex
import sys
from pathlib import Path

import pytest

from tests.integration.support import write_fast_config
from tests.procs import REPO, rider_cmd, run_bounded, running_daemon

README = (REPO / "README.md").read_text()
BLOCK = re.compile(r"```(\w+)\n(.*?)```", re.S)
RUN_TIMEOUT_S = 120


def blocks(lang: str) -> list[str]:
    return [body for kind, body in BLOCK.findall(README) if kind == lang]


def quick_start_rider_lines() -> list[str]:
    """The `rider …` lines of the quick start, without their comments."""
    lines = []
    for body in blocks("sh"):
        for line in body.splitlines():
            command = line.split("#", 1)[0].strip()
            if command.startswith("rider "):
                lines.append(command)
    return lines


def outputs() -> dict[str, str]:
    """The README's real output blocks, by the command that printed them."""
    found = re.findall(r"<!-- output: (.*?) -->\n```\n(.*?)```", README, re.S)
    return dict(found)


def kinds(text: str) -> list[str]:
    """The kinds of `rider events` lines: times, ids and seq numbers differ from run to run (a
    command retried under load is recorded once more, as a repeat), the kinds do not."""
    return [line.split()[3] for line in text.splitlines() if line.strip()]


def test_readme_has_the_examples_this_test_runs() -> None:
    assert "make run" in README and "make test" in README
    assert len(quick_start_rider_lines()) >= 6
    assert len(blocks("python")) == 1
    assert set(outputs()) <= set(quick_start_rider_lines())


def test_the_readme_is_a_front_door_not_a_manual() -> None:
    """At most 150 lines: what it is, the two commands, an example, the layout, links."""
    assert len(README.splitlines()) <= 150


@pytest.mark.integration
def test_quick_start_rider_commands_work_in_order(tmp_path: Path) -> None:
    config = write_fast_config(tmp_path)
    with running_daemon(tmp_path, extra=["--config", str(config)]) as daemon:
        env = {**os.environ, "RIDER_CONNECT": daemon.endpoint}
        printed: dict[str, str] = {}
        for line in quick_start_rider_lines():
            args = shlex.split(line)[1:]
            linked = rider_cmd("--zenoh-config", str(daemon.zenoh_config), *args)
            done = run_bounded(linked, timeout=RUN_TIMEOUT_S, env=env)
            assert done.returncode == 0, f"{line}: {done.stderr}{done.stdout}"
            printed[line] = done.stdout
        with daemon.rider() as r:
            status = r.status()
    assert status.estop.active  # the quick start pressed the E-stop
    # The event history shown in the README is what this run records (times and ids differ).
    for command, shown in outputs().items():
        assert kinds(printed[command]) == kinds(shown), printed[command]
    assert status.session is not None and status.session.revolutions_done == 3


@pytest.mark.integration
def test_python_example_runs_a_session(tmp_path: Path) -> None:
    config = write_fast_config(tmp_path)
    with running_daemon(tmp_path, extra=["--config", str(config)]) as daemon:
        code = blocks("python")[0].replace("tcp/127.0.0.1:7447", daemon.endpoint)
        code = code.replace(
            'Rider("m1", ', f'Rider("m1", zenoh_config_path=Path({str(daemon.zenoh_config)!r}), '
        )
        done = run_bounded(
            [sys.executable, "-c", "from pathlib import Path\n" + code], timeout=RUN_TIMEOUT_S
        )
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "DONE 3"
