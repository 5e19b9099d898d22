"""The way a command travels stays short (issue 54): `rider home` → the machine's reply, traced
through every thread of a real daemon and the Rider's CLI (tests/reply_path.py says how)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
MAIN_LINE_MAX = 15
"""Files on the stacks that carry the command at its hand-offs: the CLI to the query, the
Zenoh callback to the loop, the loop to the state machine's decision, the reply. (15 since the
command queue's thread, `Deferred`, became a module of its own, service/bus/deferred.py, shared
with the reply outbox: the same hand-offs, one more file on the stack.)"""

HANDLER_CROSSINGS = 1
"""Calls between the state machine (machine.py) and its handlers (handlers.py) for a Home:
the machine hands the command to its handler once, and the handler calls nothing back."""


@pytest.fixture(scope="module")
def path() -> dict:
    done = subprocess.run(
        [sys.executable, "-m", "tests.reply_path", "--json"],
        cwd=REPO, capture_output=True, text=True, timeout=240, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.splitlines()[-1])


@pytest.mark.integration
def test_a_home_is_answered_through_the_state_machine(path: dict) -> None:
    assert path["codes"]["home"] == 0, path["codes"]
    assert "service/core/statemachine/machine.py" in path["files"]
    assert path["files"][0].startswith("rider/") and path["files"][-1].startswith("rider/")


@pytest.mark.integration
def test_the_main_line_of_a_home_is_short(path: dict) -> None:
    assert path["line"][0] == "rider/cli.py"
    assert "service/core/statemachine/machine.py" in path["line"]
    assert path["line_count"] <= MAIN_LINE_MAX, "\n".join(path["line"])


@pytest.mark.integration
def test_the_state_machine_hands_a_home_to_its_handler_once(path: dict) -> None:
    assert path["handler_crossings"] == HANDLER_CROSSINGS, path["crossings"]
    assert "machine.py:handle -> handlers.py:home" in path["crossings"]
