"""The Events panel in headless Chromium: the machine's history, newest first, with a filter.

Needs Debian's `chromium` and the `playwright` package; skipped with the reason otherwise.
"""

from __future__ import annotations

from typing import Any

import pytest

from tests.ui.conftest import shot
from tests.ui.test_page import SHORT, open_page
from tests.ui.uiproc import UiServer, request

sync_api = pytest.importorskip(
    "playwright.sync_api", reason="Playwright is not installed: pip install playwright"
)
expect = sync_api.expect

pytestmark = pytest.mark.integration


def test_events_panel_lists_the_history_and_filters_by_kind(page: Any, ui: UiServer) -> None:
    open_page(page, ui)
    rows = page.locator("#events-rows tr")
    expect(page.locator("#events-rows tr[data-kind='daemon_start']")).to_have_count(1)
    page.evaluate("riderUI.send('pause')")  # refused: a `command` event with the reason
    refused = page.locator("#events-rows tr[data-kind='command']").first
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
    expect(page.locator("#events-rows tr[data-kind='command']")).to_have_count(1)


def test_history_route_refuses_an_unknown_kind(ui: UiServer) -> None:
    status, body = request(ui.port, "GET", "/api/history?kind=bogus")
    assert status == 400
    assert body["error"]["path"] == "?kind"
