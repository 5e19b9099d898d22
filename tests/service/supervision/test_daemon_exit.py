"""The shutdown deadline: a stop that hangs still ends the process, outputs safe first."""

from __future__ import annotations

import sys

import pytest

from tests.procs import run_bounded

SCRIPT = """
import time
from ride_machine.sim.hal import SimHal
from ride_machine.service.supervision.daemon import _exit_now

hal = SimHal(time.monotonic)
hal.scan_outputs(hal.outputs.__class__(ro=dict.fromkeys(hal.outputs.ro, True)))
assert hal.outputs.any_on()
real_safe = hal.force_all_outputs_safe

def safe_and_report():
    real_safe()
    print("safe", not hal.outputs.any_on(), flush=True)

hal.force_all_outputs_safe = safe_and_report
_exit_now(hal)
print("not reached", flush=True)
"""


@pytest.mark.hazard("H03")
def test_exit_deadline_forces_outputs_safe_then_ends_the_process() -> None:
    done = run_bounded([sys.executable, "-c", SCRIPT], timeout=60)
    assert done.returncode == 1
    assert done.stdout.split() == ["safe", "True"]
    assert "event=shutdown_stuck" in done.stderr
