"""The operator page in a real headless Chromium against a real daemon on the simulator.

Each stage leaves a screenshot in test-artifacts/ui/. Needs Debian's `chromium` and the
`playwright` package (never `playwright install`); skipped with the reason otherwise.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import pytest

from tests.procs import Daemon, running_daemon
from tests.ui.conftest import shot
from tests.ui.uiproc import FAST_CONFIG, UiServer, request, running_ui, start_ui

sync_api = pytest.importorskip(
    "playwright.sync_api", reason="Playwright is not installed: pip install playwright"
)
expect = sync_api.expect

pytestmark = pytest.mark.integration

RIDE_S = 60_000  # ms: bounds for whole motions on a loaded machine, not timing asserts
SHORT = 10_000


def state_is(page: Any, state: str, timeout: int = SHORT) -> None:
    expect(page.locator("#state")).to_have_attribute("data-state", state, timeout=timeout)


def confirm(page: Any, contains: str) -> None:
    dialog = page.locator("#confirm")
    expect(dialog).to_be_visible()
    expect(page.locator("#confirm-text")).to_contain_text(contains)
    page.click("#confirm-yes")
    expect(dialog).to_be_hidden()


def open_page(page: Any, ui: UiServer, host: str = "127.0.0.1") -> None:
    page.goto(f"http://{host}:{ui.port}")
    expect(page.locator("#link-machine")).to_have_attribute("data-up", "true", timeout=SHORT)


def history_has(page: Any, predicate: str) -> bool:
    return bool(page.evaluate(f"riderUI.ui.history.some(s => {predicate})"))


def fresh_then_start_refused(page: Any, ui: UiServer) -> None:
    """Stages 01-02: a fresh machine asks for calibration and refuses a Start."""
    open_page(page, ui)
    state_is(page, "WARNING_NEEDS_CALIBRATION")
    expect(page.locator("#state-card")).to_have_attribute("data-tone", "warn")
    expect(page.locator("#banner-warn")).to_contain_text("Not calibrated")
    expect(page.locator("#d-period")).to_have_text("10.0 ms", timeout=SHORT)
    expect(page.locator("#io-estop")).to_be_visible()
    expect(page.locator("#cmd-pause")).to_be_disabled()
    expect(page.locator("#cmd-resume")).to_be_disabled()
    shot(page, "01-fresh-machine")

    # Start is accepted in this state by the table, but the machine refuses it: not calibrated.
    page.click("#cmd-start")
    confirm(page, "Start the session?")
    result = page.locator("#cmd-result")
    expect(result).to_contain_text("NOT_CALIBRATED")
    expect(result).to_contain_text("not calibrated")
    expect(result).to_have_attribute("data-ok", "false")
    shot(page, "02-start-refused-not-calibrated")


def calibrate_then_home(page: Any) -> None:
    """Stages 03-05: both calibrations to their completion notices, then Home."""
    result = page.locator("#cmd-result")
    page.click("#cmd-calibrate-tilt")
    expect(page.locator("#calibrated")).to_have_text("tilt ✔ rotate ✘", timeout=RIDE_S)
    # The page waits for the completion notice of its own transaction, not for a state.
    expect(result).to_contain_text("finished: DONE", timeout=RIDE_S)
    expect(page.locator("#calibrated")).to_have_attribute(
        "title", re.compile(r"tilt: offset .* counts/° \(measured"), timeout=SHORT
    )
    page.click("#cmd-calibrate-rotate")
    expect(page.locator("#calibrated")).to_have_text("tilt ✔ rotate ✔", timeout=RIDE_S)
    assert history_has(page, "s.state === 'CALIBRATING'")
    shot(page, "03-calibrated")

    page.click("#cmd-home")
    expect(page.locator("#confirm-text")).to_contain_text("Home both axes?")
    shot(page, "04-confirm-home")
    confirm(page, "Home both axes?")
    expect(page.locator("#homed")).to_have_text("tilt ✔ rotate ✔", timeout=RIDE_S)
    state_is(page, "IDLE", RIDE_S)
    expect(page.locator("#state-card")).to_have_attribute("data-tone", "ok")
    shot(page, "05-homed")


def run_the_default_session(page: Any) -> None:
    """Stages 06-07: the default session from Start to DONE, tilt and history plotted."""
    result = page.locator("#cmd-result")
    page.select_option("#session-select", "default")
    page.click("#cmd-start")
    confirm(page, "Default: tilt 45°, 3 revolutions CW")
    state_is(page, "RUNNING")
    expect(page.locator("#session-name")).to_have_text("default")
    expect(page.locator("#cmd-pause")).to_be_enabled()
    expect(page.locator("#cmd-start")).to_be_disabled()
    expect(page.locator("#io-rotateRelay")).to_have_attribute("data-on", "true", timeout=RIDE_S)
    # A revolution counted; a loaded host may show 2 / 3 first (updates coalesce; run 77).
    expect(page.locator("#revs")).to_have_text(re.compile(r"^[123] / 3$"), timeout=RIDE_S)
    shot(page, "06-running")

    state_is(page, "DONE", RIDE_S)
    expect(page.locator("#revs")).to_have_text("3 / 3")
    expect(result).to_have_text("Start finished: DONE (session complete)", timeout=SHORT)
    tilt = float(page.locator("#tilt-value").inner_text().rstrip("°"))
    assert abs(tilt - 45.0) <= 2.0
    assert history_has(page, "s.state === 'RUNNING' && (s.rotate_bits & 2)")  # moving, plotted
    expect(page.locator("#banner-fault")).to_be_hidden()
    shot(page, "07-done")


def estop_pressed_released_and_pressed_again(page: Any, fast_daemon: Daemon) -> None:
    """Stages 08-09: the E-stop in, let go (latched), and in again under the Home dialog."""
    lamp = page.locator("#io-estop")
    level_before = lamp.get_attribute("data-on")
    with fast_daemon.rider() as r:
        r.sim("estop", pressed=True)
        expect(page.locator("#banner-fault")).to_be_visible()
        expect(page.locator("#fault-title")).to_have_text("E-STOP PRESSED")
        state_is(page, "FAULT_ESTOP")
        expect(page.locator("#state-card")).to_have_attribute("data-tone", "fault")
        expect(lamp).not_to_have_attribute("data-on", level_before or "")
        expect(page.locator("#cmd-home")).to_be_disabled()  # refused while the E-stop is in
        expect(page.locator("#cmd-check-home")).to_be_enabled()
        shot(page, "08-estop-pressed")

        r.sim("estop", pressed=False)
        expect(page.locator("#fault-title")).to_have_text("E-STOP LATCHED")
        expect(page.locator("#cmd-home")).to_be_enabled()
        expect(page.locator("#cmd-resume")).to_be_enabled()
        shot(page, "09-estop-released-latched")

        # The E-stop goes in again while the operator is still reading the Home dialog.
        page.click("#cmd-home")
        expect(page.locator("#confirm")).to_be_visible()
        r.sim("estop", pressed=True)
        expect(page.locator("#fault-title")).to_have_text("E-STOP PRESSED")
        confirm(page, "Home both axes?")
        expect(page.locator("#cmd-result")).to_have_text("Home not sent: E-stop active")
        state_is(page, "FAULT_ESTOP")


def test_operator_calibrates_homes_runs_a_session_and_sees_the_estop(
    page: Any, ui: UiServer, fast_daemon: Daemon
) -> None:
    fresh_then_start_refused(page, ui)
    calibrate_then_home(page)
    run_the_default_session(page)
    estop_pressed_released_and_pressed_again(page, fast_daemon)


def test_a_command_refused_in_the_wrong_state_shows_the_machine_error(
    page: Any, ui: UiServer
) -> None:
    open_page(page, ui)
    state_is(page, "WARNING_NEEDS_CALIBRATION")
    pause = page.locator("#cmd-pause")
    expect(pause).to_be_disabled()
    expect(pause).to_have_accessible_description("accepted in CALIBRATING, HOMING, RUNNING")
    # A page whose view is a moment old can still send it: the machine has the last word.
    page.evaluate("riderUI.send('pause')")
    result = page.locator("#cmd-result")
    expect(result).to_contain_text("Pause refused — WRONG_STATE")
    expect(result).to_contain_text("not accepted in state WARNING_NEEDS_CALIBRATION")
    expect(result).to_have_attribute("data-ok", "false")
    shot(page, "10-refused-wrong-state")


def test_uploaded_sessions_are_checked_before_they_can_be_started(
    page: Any, ui: UiServer, tmp_path: Path
) -> None:
    open_page(page, ui)
    broken = tmp_path / "broken.json"
    broken.write_text("{not json")
    page.set_input_files("#session-file", str(broken))
    expect(page.locator("#cmd-result")).to_contain_text("broken.json: not valid JSON")

    empty = tmp_path / "empty.json"
    empty.write_text(json.dumps({"name": "empty", "steps": []}))
    page.set_input_files("#session-file", str(empty))
    expect(page.locator("#cmd-result")).to_contain_text("/session/steps")
    expect(page.locator("#cmd-result")).to_have_attribute("data-ok", "false")

    good = tmp_path / "spin.json"
    good.write_text(json.dumps({"name": "spin", "steps": [{"kind": "rotate", "revolutions": 2}]}))
    page.set_input_files("#session-file", str(good))
    expect(page.locator("#cmd-result")).to_contain_text("session “spin” ready for Start")
    expect(page.locator("#session-select")).to_have_value("upload-1")
    expect(page.locator("#session-select option:checked")).to_contain_text("Uploaded: spin")


@pytest.mark.hazard("H49")
def test_monitor_mode_shows_everything_and_sends_nothing(
    page: Any, tmp_path: Path, fast_daemon: Daemon
) -> None:
    with running_ui(tmp_path, fast_daemon, monitor=True) as monitor:
        open_page(page, monitor)
        state_is(page, "WARNING_NEEDS_CALIBRATION")
        expect(page.locator("#mode-badge")).to_be_visible()
        expect(page.locator("#commands")).to_be_hidden()
        for button in page.locator("#buttons button").all():
            expect(button).to_be_disabled()
        expect(page.locator("#io-estop")).to_be_visible()
        expect(page.locator("#d-period")).to_have_text("10.0 ms", timeout=SHORT)
        shot(page, "11-monitor")

        log_before = fast_daemon.log()
        # Home would move the machine at once if it ever reached it.
        assert page.evaluate("riderUI.send('home').then(r => r.error.code)") == "MONITOR"
        status, body = request(monitor.port, "POST", "/api/cmd/home", {})
        assert status == 403
        assert body["error"]["code"] == "MONITOR"
        with fast_daemon.rider() as r:
            assert r.status().state.value == "WARNING_NEEDS_CALIBRATION"
        assert fast_daemon.log().count("event=state") == log_before.count("event=state")


def test_lost_machine_is_shown_and_the_page_recovers_when_it_returns(
    page: Any, tmp_path: Path
) -> None:
    fast = ["--config", str(FAST_CONFIG)]
    with running_daemon(tmp_path, extra=fast) as daemon, running_ui(tmp_path, daemon) as ui:
        open_page(page, ui)
        state_is(page, "WARNING_NEEDS_CALIBRATION")
        expect(page.locator("#banner-lost")).to_be_hidden()
        daemon.stop()

        expect(page.locator("#banner-lost")).to_be_visible(timeout=SHORT)
        expect(page.locator("#lost-reason")).to_contain_text("machine m1")
        expect(page.locator("#state")).to_have_text("NO CONNECTION")
        expect(page.locator("#link-machine")).to_have_attribute("data-up", "false")
        expect(page.locator("#link-server")).to_have_attribute("data-up", "true")
        for button in page.locator("#buttons button").all():
            expect(button).to_be_disabled()
        shot(page, "12-machine-lost")

        port = int(daemon.endpoint.rsplit(":", 1)[1])
        with running_daemon(tmp_path, extra=fast, port=port):
            expect(page.locator("#banner-lost")).to_be_hidden(timeout=RIDE_S)
            state_is(page, "WARNING_NEEDS_CALIBRATION")
            expect(page.locator("#cmd-calibrate-tilt")).to_be_enabled()
            shot(page, "13-machine-back")


def test_lost_ui_server_is_shown_and_the_page_reconnects_by_itself(
    page: Any, tmp_path: Path, fast_daemon: Daemon
) -> None:
    first = start_ui(tmp_path, fast_daemon)
    try:
        open_page(page, first)
        state_is(page, "WARNING_NEEDS_CALIBRATION")
        assert first.stop() == 0
    finally:
        first.stop()
    expect(page.locator("#banner-lost")).to_be_visible(timeout=SHORT)
    expect(page.locator("#lost-reason")).to_contain_text("UI server")
    expect(page.locator("#link-server")).to_have_attribute("data-up", "false")
    shot(page, "14-ui-server-lost")

    # It comes back read-only: the page follows the server's new options by itself.
    with running_ui(tmp_path, fast_daemon, port=first.port, monitor=True):
        expect(page.locator("#banner-lost")).to_be_hidden(timeout=RIDE_S)
        expect(page.locator("#link-server")).to_have_attribute("data-up", "true")
        state_is(page, "WARNING_NEEDS_CALIBRATION")
        expect(page.locator("#mode-badge")).to_be_visible()
        expect(page.locator("#commands")).to_be_hidden()
