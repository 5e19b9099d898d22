"""The Events panel in headless Chromium: the machine's history, newest first, with a filter.

Needs Debian's `chromium` and the `playwright` package; skipped with the reason otherwise.
"""

from __future__ import annotations

import re
from typing import Any

import pytest

from ride_machine.schema.status import MachineState
from tests.procs import Daemon
from tests.ui.conftest import shot
from tests.ui.test_page import RIDE_S, SHORT, open_page
from tests.ui.uiproc import UiServer, request

sync_api = pytest.importorskip(
    "playwright.sync_api", reason="Playwright is not installed: pip install playwright"
)
expect = sync_api.expect

pytestmark = pytest.mark.integration


def test_events_panel_lists_the_history_and_filters_by_kind(page: Any, ui: UiServer) -> None:
    open_page(page, ui)
    rows = page.locator("#events-rows > [data-kind]")
    expect(page.locator("#events-rows [data-kind='daemon_start']")).to_have_count(1)
    page.evaluate("riderUI.send('pause')")  # refused: a `command` event with the reason
    refused = page.locator("#events-rows [data-kind='command']").first
    expect(refused).to_contain_text("Pause", timeout=SHORT)
    expect(refused).to_contain_text("refused WRONG_STATE")
    # Newest first: the refused command is above the daemon's start.
    expect(rows.first).to_have_attribute("data-kind", "command")
    expect(rows.last).to_have_attribute("data-kind", "daemon_start")
    page.select_option("#events-kind", "daemon_start")
    expect(rows).to_have_count(1)
    expect(rows.first).to_have_attribute("data-kind", "daemon_start")
    shot(page, "40-events-filtered")
    page.select_option("#events-kind", "")
    expect(page.locator("#events-rows [data-kind='command']")).to_have_count(1)


def test_history_route_refuses_an_unknown_kind(ui: UiServer) -> None:
    status, body = request(ui.port, "GET", "/api/history?kind=bogus")
    assert status == 400
    assert body["error"]["path"] == "?kind"


STAMP = r"\d{4}-\d\d-\d\d \d\d:\d\d:\d\d\.\d{3}"
"""`rider events`' time format (local time, milliseconds): the page uses it everywhere."""


def test_events_and_the_command_log_tell_the_time_as_rider_events_does(
    page: Any, ui: UiServer, fast_daemon: Daemon
) -> None:
    open_page(page, ui)
    page.evaluate("riderUI.send('check/home')")
    row = page.locator("#events-rows [data-kind='command']").first
    expect(row).to_be_visible(timeout=SHORT)
    logged = page.locator("#cmd-log li").first.inner_text()
    assert re.match(f"^{STAMP} Check home: ", logged), logged
    shown = row.locator(".ev-time").inner_text()
    seq = row.locator(".ev-seq").inner_text().lstrip("#")
    assert re.fullmatch(STAMP, shown), shown
    cli = fast_daemon.cli("events", "--kind", "command")
    line = next(x for x in cli.stdout.splitlines() if f" #{seq} " in x)
    assert line.startswith(shown + " "), (line, shown)  # the same instant, the same text


def test_a_rider_that_leaves_at_rest_is_no_incident_one_lost_mid_motion_is(
    page: Any, ui: UiServer, fast_daemon: Daemon
) -> None:
    """As `rider start --wait` does: a motion to its end, then the Rider's session closes.
    Only a Rider gone while its motion runs is shown as an incident, in the CLI and here."""
    done = fast_daemon.cli("calibrate", "tilt", "--wait", timeout=RIDE_S / 1000)
    assert done.returncode == 0, done.stderr
    with fast_daemon.rider() as supervising:
        assert supervising.calibrate_tilt().state is MachineState.CALIBRATING
    with fast_daemon.rider(supervise=False) as r:
        r.wait_for({MachineState.PAUSED}, SHORT / 1000)  # its loss paused the motion

    cli = fast_daemon.cli("events", "--kind", "rider_lost").stdout.splitlines()
    assert "left at rest" in cli[0] and "mid-motion" not in cli[0], cli
    assert "lost mid-motion: policy pause applied" in cli[-1], cli

    open_page(page, ui)
    page.select_option("#events-kind", "rider_lost")
    rows = page.locator("#events-rows > [data-kind='rider_lost']")
    at_rest = rows.filter(has_text="left at rest")
    mid_motion = rows.filter(has_text="lost mid-motion")
    expect(mid_motion).to_have_count(1, timeout=SHORT)
    expect(at_rest).to_have_count(1)
    expect(at_rest).to_have_attribute("data-tone", "")
    expect(mid_motion).to_have_attribute("data-tone", "fault")
    expect(at_rest.locator(".ev-kind")).to_have_css("font-weight", "400")
    expect(mid_motion.locator(".ev-kind")).to_have_css("font-weight", "600")
    shot(page, "41-rider-left-vs-lost")


def test_the_panel_reads_a_calibration_and_its_rider_for_people(
    page: Any, ui: UiServer, fast_daemon: Daemon
) -> None:
    """Issue 58, point 11: `rotate calibrated: revolution 2.000 s, home arc 20.0° (measured)`
    and `from anonymous · 9d617a`, where the panel showed a dict of 16-digit floats and the
    Rider's 32-digit session id (the text comes from the server: common/event_words.py)."""
    for axis in ("tilt", "rotate"):
        done = fast_daemon.cli("calibrate", axis, "--wait", timeout=RIDE_S / 1000)
        assert done.returncode == 0, done.stderr
    open_page(page, ui)
    page.select_option("#events-kind", "calibration")
    rotate = page.locator("#events-rows > [data-kind='calibration']", has_text="rotate")
    expect(rotate.locator(".ev-text")).to_have_text(
        re.compile(r"^rotate calibrated: revolution \d+\.\d{3} s, home arc \d+\.\d° \(measured\)$"),
        timeout=SHORT,
    )
    page.select_option("#events-kind", "command")
    commands = page.locator("#events-rows > [data-kind='command'] .ev-text")
    expect(commands.first).to_contain_text("Calibrate rotate accepted from anonymous · ")
    for text in commands.all_inner_texts():
        assert re.search(r"from anonymous · [0-9a-f]{6}( |,|:|$)", text), text
        assert not re.search(r"[0-9a-f]{16,}|[{}]|\d\.\d{4,}", text), text
    shot(page, "42-events-for-people")
