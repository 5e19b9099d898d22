"""The operator page for every operator: on a phone, by keyboard alone, and by axe-core's rules.

Headless Chromium against a real daemon; axe-core comes from tests/js (pinned by its
package-lock.json). What is measured (axe's violations by impact, the page's width at each
phone size) goes to test-artifacts/ui/measured.json beside the screenshots.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from tests.nodejs import node_module
from tests.ui.conftest import record, shot
from tests.ui.test_page import SHORT, open_page, state_is
from tests.ui.uiproc import UiServer

sync_api = pytest.importorskip(
    "playwright.sync_api", reason="Playwright is not installed: pip install playwright"
)
expect = sync_api.expect

pytestmark = pytest.mark.integration

PHONE_WIDTHS = (390, 360, 414)
BLOCKING = ("serious", "critical")
TAB_LIMIT = 60
"""Tab presses before giving up on reaching a control: the page has about 15."""


def axe(page: Any, context: str = "document") -> list[dict[str, Any]]:
    """axe-core's violations on the page (or on the `context` selector), each with its
    impact, how many elements and which."""
    if not page.evaluate("typeof axe !== 'undefined'"):
        page.add_script_tag(path=str(node_module("axe-core") / "axe.min.js"))
    found: list[dict[str, Any]] = page.evaluate(
        """async (context) => {
          const where = context === "document" ? document : context;
          const r = await axe.run(where, { resultTypes: ["violations"] });
          return r.violations.map((v) => ({
            id: v.id, impact: v.impact, nodes: v.nodes.length,
            targets: v.nodes.map((n) => n.target.join(" ")).slice(0, 12),
          }));
        }""",
        context,
    )
    return found


def by_impact(violations: list[dict[str, Any]]) -> dict[str, int]:
    counts: dict[str, int] = {}
    for v in violations:
        counts[v["impact"]] = counts.get(v["impact"], 0) + 1
    return counts


def overflow(page: Any) -> dict[str, Any]:
    """The document's scroll and client widths, and the elements reaching past its edge."""
    found: dict[str, Any] = page.evaluate(
        """() => {
          const root = document.documentElement;
          const edge = root.clientWidth;
          const wide = [...document.querySelectorAll("body *")]
            .filter((el) => el.getBoundingClientRect().right > edge + 0.5)
            .map((el) => el.id ? `#${el.id}` : `${el.tagName.toLowerCase()}.${el.className}`);
          return { scroll: root.scrollWidth, client: edge, wide: wide.slice(0, 8) };
        }"""
    )
    return found


def busy_page(page: Any) -> None:
    """A refused command: a long line in the events and one in the command log."""
    page.evaluate("riderUI.send('pause')")
    expect(page.locator("#cmd-result")).to_contain_text("Pause refused", timeout=SHORT)
    expect(page.locator("#events-rows [data-kind='command']").first).to_be_visible(timeout=SHORT)


def test_the_page_fits_a_phone_without_scrolling_sideways(phone: Any, ui: UiServer) -> None:
    open_page(phone, ui)
    state_is(phone, "WARNING_NEEDS_CALIBRATION")
    busy_page(phone)
    widths = {}
    for width in PHONE_WIDTHS:
        phone.set_viewport_size({"width": width, "height": 844})
        expect(phone.locator("#events-rows [data-kind='command']").first).to_be_visible()
        measured = overflow(phone)
        widths[width] = measured
        shot(phone, f"phone-{width}")
        assert measured["scroll"] == measured["client"] == width, measured
    record("phone_widths", widths)


def test_axe_finds_nothing_serious_on_a_desktop_or_a_phone(
    page: Any, phone: Any, ui: UiServer
) -> None:
    counts = {}
    for name, pg in (("1280", page), ("390", phone)):
        open_page(pg, ui)
        state_is(pg, "WARNING_NEEDS_CALIBRATION")
        busy_page(pg)
        found = axe(pg)
        counts[name] = {"by_impact": by_impact(found), "violations": found}
        shot(pg, f"axe-{name}")
    record("axe", counts)
    for name, entry in counts.items():
        blocking = [v for v in entry["violations"] if v["impact"] in BLOCKING]
        assert not blocking, f"at {name} px: {json.dumps(blocking, indent=1)}"


def test_every_state_colour_keeps_its_text_readable(page: Any, ui: UiServer) -> None:
    """The state tile in each of its colours (ok, moving, warn, fault, no connection), shown
    from a frozen copy of the status, so no update repaints it while axe reads it."""
    open_page(page, ui)
    state_is(page, "WARNING_NEEDS_CALIBRATION")
    page.evaluate(
        """() => {
          const ui = riderUI.ui;
          ui.es.close();
          ui.server.lastMsg = Infinity;  // the stream is closed on purpose: no watchdog
          ui.status = { ...ui.status, previous_state: "HOMING" };
        }"""
    )
    seen = {}
    for state, tone in (
        ("IDLE", "ok"),
        ("RUNNING", "moving"),
        ("PAUSED", "warn"),
        ("FAULT_HW", "fault"),
        (None, "unknown"),
    ):
        page.evaluate(
            """(state) => {
              const ui = riderUI.ui;
              if (state) ui.status = { ...ui.status, state };
              ui.link = { ...ui.link, up: state !== null };
              riderUI.render();
            }""",
            state,
        )
        expect(page.locator("#state-card")).to_have_attribute("data-tone", tone)
        found = axe(page, "#state-card")
        seen[tone] = by_impact(found)
        assert not [v for v in found if v["impact"] in BLOCKING], (tone, found)
    record("axe_state_tones", seen)


def focus_walk(page: Any) -> list[dict[str, Any]]:
    """Tab from the top of the page until focus comes round again: each stop's id and
    whether a focus ring shows (an outline at least 2 px wide, 3:1 against what it sits on;
    a visually hidden input shows it on its label)."""
    page.evaluate("document.activeElement && document.activeElement.blur()")
    stops: list[dict[str, Any]] = []
    for _ in range(TAB_LIMIT):
        page.keyboard.press("Tab")
        stop: dict[str, Any] = page.evaluate(FOCUS_PROBE)
        if stop["id"] is None or (stops and stop["id"] == stops[0]["id"]):
            if stops:
                break
            continue
        stops.append(stop)
    return stops


FOCUS_PROBE = """() => {
  const el = document.activeElement;
  if (!el || el === document.body) return { id: null };
  const shown = el.getClientRects().length && el.offsetWidth > 1 ? el : el.closest("label") || el;
  const style = getComputedStyle(shown);
  const rgb = (c) => (c.match(/[\\d.]+/g) || []).map(Number);
  const lum = ([r, g, b]) => {
    const f = (v) => { v /= 255; return v <= 0.03928 ? v / 12.92 : ((v + 0.055) / 1.055) ** 2.4; };
    return 0.2126 * f(r) + 0.7152 * f(g) + 0.0722 * f(b);
  };
  let under = shown.parentElement;
  const clear = (node) => rgb(getComputedStyle(node).backgroundColor)[3] === 0;
  while (under && clear(under)) under = under.parentElement;
  const bg = rgb(getComputedStyle(under || document.body).backgroundColor);
  const ring = rgb(style.outlineColor);
  const [hi, lo] = [lum(ring), lum(bg)].sort((a, b) => b - a);
  return {
    id: el.id || `${el.tagName.toLowerCase()}:${el.textContent.trim().slice(0, 20)}`,
    style: style.outlineStyle,
    width: parseFloat(style.outlineWidth),
    contrast: Math.round(((hi + 0.05) / (lo + 0.05)) * 100) / 100,
  };
}"""


def test_every_control_is_reached_by_tab_with_a_visible_focus_ring(page: Any, ui: UiServer) -> None:
    open_page(page, ui)
    state_is(page, "WARNING_NEEDS_CALIBRATION")
    enabled = page.eval_on_selector_all("#buttons button:enabled", "bs => bs.map(b => b.id)")
    assert len(enabled) >= 4
    stops = focus_walk(page)
    reached = [s["id"] for s in stops]
    record("focus_order", stops)
    for wanted in [*enabled, "session-select", "session-file", "events-kind"]:
        assert wanted in reached, f"{wanted} is not reached by Tab: {reached}"
    faint = [s for s in stops if s["style"] == "none" or s["width"] < 2 or s["contrast"] < 3]
    assert not faint, f"focus rings too faint to see: {faint}"
    page.focus("#cmd-check-home")
    shot(page, "focus-ring-1280")


def test_the_keyboard_alone_sends_a_command_uploads_a_session_and_cancels_a_start(
    page: Any, ui: UiServer, tmp_path: Path
) -> None:
    # Intercept file choosers from the start (Playwright turns it on with the first listener),
    # so the key press below cannot come before the interception.
    page.on("filechooser", lambda chooser: None)
    open_page(page, ui)
    state_is(page, "WARNING_NEEDS_CALIBRATION")
    result = page.locator("#cmd-result")

    page.focus("#cmd-check-home")
    page.keyboard.press("Enter")
    expect(result).to_contain_text("Check home:", timeout=SHORT)

    session = tmp_path / "keys.json"
    steps = [{"kind": "rotate", "revolutions": 1}]
    session.write_text(json.dumps({"name": "keys", "steps": steps}))
    stops = [s["id"] for s in focus_walk(page)]
    assert "session-file" in stops
    page.focus("#session-file")
    with page.expect_file_chooser(timeout=SHORT) as chooser:
        page.keyboard.press("Space")
    chooser.value.set_files(str(session))
    expect(result).to_contain_text("session “keys” ready for Start", timeout=SHORT)

    page.focus("#cmd-start")
    page.keyboard.press("Enter")
    expect(page.locator("#confirm")).to_be_visible()
    expect(page.locator("#confirm-no")).to_be_focused()  # the safe answer is the default
    page.keyboard.press("Escape")
    expect(page.locator("#confirm")).to_be_hidden()
    expect(result).to_contain_text("ready for Start")  # nothing was sent
