"""`AsyncRider`'s methods are typed: mypy sees each one's real signature (a wrong call is an
error) and nothing that comes out of them is `Any` (`--disallow-any-expr` over a caller that
uses every method, each result checked with `assert_type`)."""

from __future__ import annotations

from pathlib import Path

from mypy import api

from tests.procs import REPO

CALLER = """
from typing import assert_type

from ride_machine.common.event_summary import EventSummary
from ride_machine.rider.client import AsyncRider, Listing, MachineInfo, Subscription, Update
from ride_machine.rider.pinning import Holders
from ride_machine.schema.axes import AxisRecord
from ride_machine.schema.calibration import CalibrationRecord
from ride_machine.schema.commands import CheckResult, Command, Reply
from ride_machine.schema.completion import Completion
from ride_machine.schema.diag import CycleDiag
from ride_machine.schema.events import Event, EventPage, EventQuery
from ride_machine.schema.findings import Findings
from ride_machine.schema.io import IoValue
from ride_machine.schema.params import ParamValue
from ride_machine.schema.sim import SimWorldState
from ride_machine.schema.status import MachineState, Status


def on_update(update: Update) -> None:
    pass


async def caller() -> None:
    async with AsyncRider("m1", connect=["tcp/127.0.0.1:7447"], timeout=1.0) as r:
        assert_type(r.rider_id, str)
        assert_type(await r.no_link_hint(), str)
        assert_type(await r.pick_machine(motion=True), str)
        assert_type(await r.resolve_machine(), str)
        assert_type(await r.machines(), Listing[MachineInfo])
        assert_type(await r.holders("m1"), Holders)
        assert_type(await r.new_transaction_id(), str)
        assert_type(await r.command(Command.HOME, check=False, timeout=2.0), Reply)
        for move in (r.calibrate_tilt, r.calibrate_rotate, r.home, r.pause, r.resume, r.stop):
            assert_type(await move(), Reply)
        assert_type(await r.start(), Reply)
        assert_type(await r.check_calibration(), CheckResult)
        assert_type(await r.check_home(), CheckResult)
        assert_type(await r.status(timeout=1.0), Status)
        assert_type(await r.io(), list[IoValue])
        assert_type(await r.axes(), list[AxisRecord])
        assert_type(await r.diag(reset=True), CycleDiag)
        assert_type(await r.validate(b""), Findings)
        assert_type(await r.calibration(), CalibrationRecord)
        assert_type(await r.set_calibration(), CalibrationRecord)
        assert_type(await r.params(), list[ParamValue])
        assert_type(await r.param("x"), ParamValue)
        assert_type(await r.set_param("x", 1, persist=True), ParamValue)
        assert_type(await r.reset_param("x"), ParamValue)
        assert_type(await r.sim("estop", pressed=True), SimWorldState)
        assert_type(await r.event_pages(EventQuery()), list[EventPage])
        assert_type(await r.events(EventQuery()), list[Event])
        assert_type(await r.events_summary(), list[EventSummary])
        assert_type(await r.subscribe(("status",), on_update), Subscription)
        assert_type(await r.done("t1"), Completion | None)
        assert_type(await r.recent_completions(), list[Completion])
        assert_type(await r.wait_done("t1", 5.0, quiet_s=1.0), Completion)
        assert_type(await r.wait_for({MachineState.IDLE}, after=1.0), Status)
        async for update in r.watch(("status",), timeout=1.0):
            assert_type(update, Update)
        async for event in r.follow_events(timeout=0.5):
            assert_type(event, Event | None)
        async for change in r.follow_machines(0.5, history=False):
            assert_type(change, tuple[str, bool] | None)
"""

WRONG = """
from ride_machine.rider.client import AsyncRider


async def caller(r: AsyncRider) -> None:
    await r.status(2.0, 3.0)
    await r.wait_done("t1", bogus=1)
    await r.home("now")
    r.watch(timeout="soon")
"""


def mypy(tmp_path: Path, source: str) -> tuple[int, str]:
    """mypy's exit status and report for `source`, with the project's settings and cache."""
    caller = tmp_path / "caller.py"
    caller.write_text(source)
    out, err, status = api.run(
        [
            "--config-file",
            str(REPO / "pyproject.toml"),
            "--cache-dir",
            str(REPO / ".mypy_cache"),
            "--follow-imports=silent",
            "--disallow-any-expr",
            "--no-error-summary",
            str(caller),
        ]
    )
    return status, out + err


def test_nothing_that_comes_out_of_the_async_rider_is_any(tmp_path: Path) -> None:
    status, report = mypy(tmp_path, CALLER)
    assert status == 0, report


def test_a_wrong_call_to_the_async_rider_is_a_type_error(tmp_path: Path) -> None:
    status, report = mypy(tmp_path, WRONG)
    assert status == 1
    errors = [line.split("error: ", 1)[1] for line in report.splitlines() if "error: " in line]
    assert len(errors) == 4, report
    assert all("[call-arg]" in e or "[arg-type]" in e for e in errors), report
