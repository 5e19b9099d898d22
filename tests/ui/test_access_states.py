"""The operator page in every state it can show, for every operator (issue 58, point 10).

- axe-core finds no serious or critical violation in any state: connecting, searching, a login
  refused, each machine state (E-stop pressed and latched, a fault, a storage warning), a
  command on its way, the Start dialog, monitor mode, the UI server lost and the machine lost.
  Losing the machine once dimmed the last known values by opacity: 2.25:1, 245 nodes.
- A button that becomes unavailable under the keyboard's focus keeps it (Start, then Pause:
  focus fell to the page's body).
- Why a button is unavailable is a visible line it is described by, reached by Tab and read by a
  screen reader (it was a tooltip, for a mouse only).

Headless Chromium against a real daemon; the states a test cannot make the machine take at will
(a fault, a storage warning, a lost login) are shown from a frozen copy of its status, as
test_access.py shows the state tile's colours. What is measured goes to
test-artifacts/ui/measured.json (`axe_states`, `lost_link`).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from tests.procs import Daemon, running_daemon
from tests.ui.conftest import record, shot
from tests.ui.test_access import BLOCKING, axe, by_impact, focus_walk
from tests.ui.test_page import RIDE_S, SHORT, open_page, state_is
from tests.ui.uiproc import FAST_CONFIG, UiServer, running_ui

sync_api = pytest.importorskip(
    "playwright.sync_api", reason="Playwright is not installed: pip install playwright"
)
expect = sync_api.expect

pytestmark = pytest.mark.integration

LEGIBLE = 4.5
"""WCAG's contrast for text of normal size (AA)."""

CONTRAST = """async () => {
  const r = await axe.run(document, {
    runOnly: ["color-contrast"], resultTypes: ["passes", "violations"],
  });
  const ratios = [];
  for (const rule of [...r.passes, ...r.violations]) {
    for (const node of rule.nodes) {
      for (const check of [...node.any, ...node.all, ...node.none]) {
        if (check.data && check.data.contrastRatio) ratios.push(check.data.contrastRatio);
      }
    }
  }
  const failing = r.violations.reduce((n, v) => n + v.nodes.length, 0);
  return { lowest: Math.min(...ratios), measured: ratios.length, failing };
}"""
"""The lowest text contrast axe measured on the page, over how many elements, and how many fail."""


def contrast(page: Any) -> dict[str, Any]:
    axe(page, "#state-card")  # loads axe-core into the page
    found: dict[str, Any] = page.evaluate(CONTRAST)
    return found


def test_the_lost_link_keeps_every_text_legible(page: Any, tmp_path: Path) -> None:
    """The machine stops: its last known values stay on the page, marked as such, not faded."""
    fast = ["--config", str(FAST_CONFIG)]
    with running_daemon(tmp_path, extra=fast) as daemon, running_ui(tmp_path, daemon) as ui:
        open_page(page, ui)
        state_is(page, "WARNING_NEEDS_CALIBRATION")
        expect(page.locator("#d-period")).to_have_text("10.0 ms", timeout=SHORT)
        live = contrast(page)
        daemon.stop()
        expect(page.locator("#banner-lost")).to_be_visible(timeout=SHORT)
        expect(page.locator("#main")).to_have_attribute("data-stale", "true")
        tags = page.locator("#main .stale-tag")
        expect(tags).to_have_count(6)  # every card but the state tile and the commands
        for tag in tags.all():
            expect(tag).to_be_visible()
        expect(page.locator("#d-period")).to_have_text("10.0 ms")  # still shown
        said = "Unavailable now: not connected to the machine"
        expect(page.locator("#commands-why")).to_have_text(said)  # once, for every button
        for button in page.locator("#buttons button").all():
            expect(button).to_have_accessible_description(said)
        expect(page.locator("#buttons .why:visible")).to_have_count(0)
        lost = contrast(page)
        found = axe(page)
        shot(page, "50-lost-link-legible")
    record("lost_link", {"live": live, "lost": lost, "by_impact": by_impact(found)})
    blocking = [v for v in found if v["impact"] in BLOCKING]
    assert not blocking, json.dumps(blocking, indent=1)
    assert lost["failing"] == 0 and lost["lowest"] >= LEGIBLE, lost


FREEZE = """() => {
  const ui = riderUI.ui;
  ui.es.close();
  ui.server.lastMsg = Infinity;  // the stream is closed on purpose: no watchdog
  window.liveStatus = ui.status;
}"""

SHOW = """([server, link, patch]) => {
  const ui = riderUI.ui;
  ui.server = { ...ui.server, ...server };
  ui.link = { ...ui.link, ...link };
  ui.status = patch === null ? null : { ...window.liveStatus, ...patch };
  ui.busy.clear();
  riderUI.render();
}"""

UP = {"up": True, "reason": ""}
SESSION = {
    "name": "default",
    "step_index": 1,
    "step_count": 2,
    "step_kind": "rotate",
    "revolutions_done": 1,
    "revolutions_total": 3,
    "tilt_target_deg": 45.0,
}
HOMED = {"calibrated": {"tilt": True, "rotate": True}, "homed": {"tilt": True, "rotate": True}}
ESTOP_IN = {"state": "FAULT_ESTOP", "estop": {"active": True, "latched": True}, **HOMED}
STATES: dict[str, tuple[dict[str, Any], dict[str, Any], dict[str, Any] | None]] = {
    "connecting": (UP, {"up": False, "reason": "connecting to the machine…"}, None),
    "searching": (
        UP,
        {"up": False, "reason": "no machine is alive on the network yet; searching…"},
        None,
    ),
    "login refused": (
        UP,
        {"up": False, "reason": "no Zenoh session: authentication refused (user bay1)"},
        None,
    ),
    "needs calibration": (UP, UP, {"state": "WARNING_NEEDS_CALIBRATION"}),
    "not home": (UP, UP, {"state": "WARNING_NOT_HOME", "calibrated": HOMED["calibrated"]}),
    "calibrating": (UP, UP, {"state": "CALIBRATING"}),
    "homing": (UP, UP, {"state": "HOMING", **HOMED}),
    "idle": (UP, UP, {"state": "IDLE", **HOMED}),
    "running": (UP, UP, {"state": "RUNNING", "session": SESSION, **HOMED}),
    "paused": (UP, UP, {"state": "PAUSED", "session": SESSION, **HOMED}),
    "done": (UP, UP, {"state": "DONE", "session": {**SESSION, "revolutions_done": 3}, **HOMED}),
    "e-stop pressed": (UP, UP, ESTOP_IN),
    "e-stop latched": (UP, UP, {**ESTOP_IN, "estop": {"active": False, "latched": True}}),
    "fault": (
        UP,
        UP,
        {
            "state": "FAULT_HW",
            "fault": {"code": "TILT_NOT_FOLLOWING", "message": "stood still", "axis": "tilt"},
            **HOMED,
        },
    ),
    "storage warning": (
        UP,
        UP,
        {"state": "IDLE", "warnings": ["STORAGE_FAILED: data_dir is read-only"], **HOMED},
    ),
    "machine lost": (
        UP,
        {"up": False, "reason": "no status from machine m1 for over 1.5 s; reconnecting…"},
        {"state": "RUNNING", "session": SESSION, **HOMED},
    ),
    "UI server lost": (
        {"up": False, "reason": "lost the connection to the UI server; reconnecting…"},
        UP,
        {"state": "IDLE", **HOMED},
    ),
}


def test_every_state_of_the_page_passes_axe(
    page: Any, ui: UiServer, fast_daemon: Daemon, tmp_path: Path
) -> None:
    open_page(page, ui)
    state_is(page, "WARNING_NEEDS_CALIBRATION")
    seen: dict[str, dict[str, int]] = {}
    failures: dict[str, Any] = {}

    def check(name: str) -> None:
        found = axe(page)
        blocking = [v for v in found if v["impact"] in BLOCKING]
        seen[name] = {**by_impact(found), "blocking_nodes": sum(v["nodes"] for v in blocking)}
        if blocking:
            failures[name] = blocking
        shot(page, f"state-{name.replace(' ', '-')}")

    # A command on its way and the Start dialog, on the live page.
    page.evaluate("riderUI.ui.busy.add('CheckHome'); riderUI.render()")
    check("command on its way")
    page.evaluate("riderUI.ui.busy.clear(); riderUI.render()")
    page.click("#cmd-start")
    expect(page.locator("#confirm")).to_be_visible()
    check("start dialog")
    page.keyboard.press("Escape")
    expect(page.locator("#confirm")).to_be_hidden()

    page.evaluate(FREEZE)
    for name, (server, link, patch) in STATES.items():
        page.evaluate(SHOW, [server, link, patch])
        check(name)

    with running_ui(tmp_path, fast_daemon, monitor=True) as monitor:
        open_page(page, monitor)
        state_is(page, "WARNING_NEEDS_CALIBRATION")
        check("monitor")
    record("axe_states", seen)
    assert not failures, json.dumps(failures, indent=1)


def test_focus_stays_when_the_pressed_button_becomes_unavailable(
    page: Any, ui: UiServer, fast_daemon: Daemon
) -> None:
    """By keyboard alone: Start, then Pause; each becomes unavailable as the machine takes it,
    and keeps the focus (it fell to the page's body), saying why it is unavailable now."""
    for step in (("calibrate", "tilt"), ("calibrate", "rotate"), ("home",)):
        done = fast_daemon.cli(*step, "--wait", timeout=RIDE_S / 1000)
        assert done.returncode == 0, done.stderr
    open_page(page, ui)
    state_is(page, "IDLE")
    start, pause = page.locator("#cmd-start"), page.locator("#cmd-pause")

    page.focus("#cmd-start")
    page.keyboard.press("Enter")
    expect(page.locator("#confirm-no")).to_be_focused()
    page.keyboard.press("Tab")
    expect(page.locator("#confirm-yes")).to_be_focused()
    page.keyboard.press("Enter")
    state_is(page, "RUNNING", RIDE_S)
    expect(start).to_be_focused()
    expect(start).to_be_disabled()
    expect(start).to_have_accessible_description(
        "accepted in DONE, IDLE, WARNING NEEDS CALIBRATION, WARNING NOT HOME"
    )

    page.keyboard.press("Tab")
    expect(pause).to_be_focused()
    page.keyboard.press("Enter")
    state_is(page, "PAUSED", RIDE_S)
    expect(pause).to_be_focused()
    expect(pause).to_be_disabled()
    expect(pause).to_have_accessible_description("accepted in CALIBRATING, HOMING, RUNNING")
    shot(page, "51-focus-kept-on-pause")

    page.keyboard.press("Enter")  # an unavailable button refuses, and says why
    expect(page.locator("#cmd-result")).to_have_text(
        "Pause not sent: accepted in CALIBRATING, HOMING, RUNNING"
    )
    page.keyboard.press("Tab")
    page.keyboard.press("Tab")  # Resume, then Stop
    expect(page.locator("#cmd-stop")).to_be_focused()
    page.keyboard.press("Enter")
    state_is(page, "DONE", RIDE_S)  # the session ended by Stop


def test_why_a_button_is_unavailable_is_seen_reached_and_read(page: Any, ui: UiServer) -> None:
    open_page(page, ui)
    state_is(page, "WARNING_NEEDS_CALIBRATION")
    buttons = page.locator("#buttons button")
    unavailable = page.eval_on_selector_all(
        "#buttons button[aria-disabled='true']", "bs => bs.map(b => b.id)"
    )
    assert {"cmd-pause", "cmd-resume"} <= set(unavailable), unavailable
    reached = [stop["id"] for stop in focus_walk(page)]
    reasons = {}
    for button in buttons.all():
        ident = button.get_attribute("id")
        assert ident in reached, f"{ident} is not reached by Tab: {reached}"
        why = page.locator(f"#why-{ident}")
        if ident in unavailable:
            expect(why).to_be_visible()
            reasons[ident] = why.inner_text()
            assert reasons[ident], ident
            expect(button).to_have_accessible_description(reasons[ident])
        else:
            expect(why).to_be_hidden()
            expect(button).to_have_accessible_description("")
        assert button.get_attribute("title") is None  # nothing said to a mouse alone
    record("unavailable_reasons", reasons)
    shot(page, "52-reasons-shown")
