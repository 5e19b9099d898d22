"""A web page must not command the ride through `rider ui`: DNS rebinding, foreign and `null`
origins, over HTTP and in a real browser whose name resolution is rebound.

A rebinding page is served from the attacker's name, which then resolves to 127.0.0.1: to the
browser the UI is that page's own origin. Chromium's `--host-resolver-rules` maps the name to
127.0.0.1, and Playwright serves the attacker's first page itself (its first DNS answer).
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from tests.procs import Daemon
from tests.ui.conftest import launched, new_page
from tests.ui.test_page import SHORT, open_page, state_is
from tests.ui.uiproc import UiServer, request, running_ui

pytestmark = pytest.mark.integration

EVIL = "rebind.test"
"""The attacker's name; the browser below resolves it to 127.0.0.1."""


def commands_recorded(daemon: Daemon) -> int:
    with daemon.rider(supervise=False) as r:
        return len(r.events(kinds=("command",)))


@pytest.mark.hazard("H49")
def test_a_rebound_host_name_can_neither_command_nor_read(
    ui: UiServer, fast_daemon: Daemon
) -> None:
    evil = f"{EVIL}:{ui.port}"
    hostile = {"Host": evil, "Origin": f"http://{evil}"}
    status, body = request(ui.port, "POST", "/api/cmd/check/home", {}, hostile)
    assert status == 403, body  # the old code: 200, the command executed
    assert (body["error"]["code"], body["error"]["path"]) == ("FOREIGN_HOST", "Host")
    status, body = request(ui.port, "POST", "/api/cmd/pause", {}, {"Host": evil})
    assert status == 403, body
    assert body["error"]["code"] == "FOREIGN_HOST"
    for path in ("/api/snapshot", "/api/config", "/api/history", "/", "/static/app.js"):
        status, body = request(ui.port, "GET", path, headers={"Host": evil})
        assert status == 403, (path, body)
        assert "WARNING_NEEDS_CALIBRATION" not in str(body)
    assert commands_recorded(fast_daemon) == 0  # nothing reached the machine
    # The names it is served on still work, with or without an Origin.
    for host in (f"127.0.0.1:{ui.port}", f"localhost:{ui.port}"):
        own = {"Host": host, "Origin": f"http://{host}"}
        status, body = request(ui.port, "POST", "/api/cmd/check/home", {}, own)
        assert status == 200, body
    assert commands_recorded(fast_daemon) == 2


@pytest.mark.hazard("H50")
def test_a_null_or_foreign_origin_cannot_command(ui: UiServer, fast_daemon: Daemon) -> None:
    for origin in ("null", "http://evil.example", f"http://127.0.0.1:{ui.port + 1}", "file://"):
        status, body = request(ui.port, "POST", "/api/cmd/check/home", {}, {"Origin": origin})
        assert status == 403, (origin, body)
        assert body["error"]["code"] == "FOREIGN_ORIGIN", (origin, body)
        status, body = request(ui.port, "POST", "/api/session", {}, {"Origin": origin})
        assert status == 403, (origin, body)
    assert commands_recorded(fast_daemon) == 0
    status, body = request(ui.port, "POST", "/api/cmd/check/home", {})  # curl: no Origin
    assert status == 200, body


def test_a_reverse_proxy_name_is_served_when_allowed(tmp_path: Path, fast_daemon: Daemon) -> None:
    with running_ui(
        tmp_path, fast_daemon, extra=["--allowed-host", "hmi.plant.example"]
    ) as proxied:
        # nginx passes the public name on (proxy_set_header Host $host) and the browser's Origin.
        proxy = {"Host": "hmi.plant.example", "Origin": "https://hmi.plant.example"}
        status, body = request(proxied.port, "POST", "/api/cmd/check/home", {}, proxy)
        assert status == 200, body
        status, _ = request(proxied.port, "GET", "/api/snapshot", headers={"Host": EVIL})
        assert status == 403
        assert "hmi.plant.example" in proxied.log()  # it says which names it answers to


@pytest.fixture(scope="module")
def rebinding_browser() -> Iterator[Any]:
    with launched(f"--host-resolver-rules=MAP {EVIL} 127.0.0.1", "--no-proxy-server") as b:
        yield b


ATTACK = """<!doctype html><title>cute cats</title><script>
// Chromium's Private Network Access keeps this public page's own requests off 127.0.0.1, but
// a window it opens on its own origin is loaded from there, and same-origin script drives it.
const w = window.open("/");
window.outcome = new Promise((done) => w.addEventListener("load", async () => {
  const post = (path) => w.fetch(path, {method: "POST", body: "{}",
    headers: {"Content-Type": "application/json"}}).then((r) => r.status, () => 0);
  const read = await w.fetch("/api/snapshot").then((r) => r.text(), () => "");
  done({home: await post("/api/cmd/home"), check: await post("/api/cmd/check/home"),
        snapshot: read, page: w.document.body.innerText.slice(0, 300)});
}));
</script>"""


@pytest.mark.hazard("H49")
def test_a_page_whose_name_rebinds_to_the_ui_cannot_press_its_buttons(
    rebinding_browser: Any, ui: UiServer, fast_daemon: Daemon
) -> None:
    evil_url = f"http://{EVIL}:{ui.port}/"
    with new_page(rebinding_browser) as page:
        # The attacker's own server answers the first load; then the name points at the UI.
        page.route(evil_url, lambda route: route.fulfill(content_type="text/html", body=ATTACK))
        page.goto(evil_url)
        page.unroute(evil_url)  # from now on the name leads to 127.0.0.1: to the UI
        outcome = page.evaluate("window.outcome")
        assert outcome["home"] == 403 and outcome["check"] == 403, outcome
        assert "WARNING_NEEDS_CALIBRATION" not in outcome["snapshot"]
        assert "FOREIGN_HOST" in outcome["page"], outcome  # not the operator page either
    assert commands_recorded(fast_daemon) == 0
    state_is_unmoved(fast_daemon)

    # The operator's own page, by either of its names, still commands the machine.
    with new_page(rebinding_browser) as page:
        open_page(page, ui, host="localhost")
        state_is(page, "WARNING_NEEDS_CALIBRATION")
        page.click("#cmd-check-home")
        expect = pytest.importorskip("playwright.sync_api").expect
        expect(page.locator("#cmd-result")).to_contain_text("Check home:", timeout=SHORT)


def state_is_unmoved(daemon: Daemon) -> None:
    with daemon.rider(supervise=False) as r:
        assert r.status().state.value == "WARNING_NEEDS_CALIBRATION"
