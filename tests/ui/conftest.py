"""Fixtures for the operator UI: a quick simulated daemon, `rider ui`, and headless Chromium."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from tests.procs import REPO, Daemon, running_daemon
from tests.ui.uiproc import FAST_CONFIG, UiServer, running_ui

ARTIFACTS = REPO / "test-artifacts" / "ui"
CHROMIUM_ARGS = [
    "--no-sandbox",
    "--headless",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
]


def chromium_path() -> str | None:
    """Debian's Chromium (or $CHROMIUM); never a browser downloaded by Playwright."""
    for candidate in (os.environ.get("CHROMIUM"), "/usr/bin/chromium"):
        if candidate and Path(candidate).exists():
            return candidate
    return shutil.which("chromium") or shutil.which("chromium-browser")


@pytest.fixture
def fast_daemon(tmp_path: Path) -> Iterator[Daemon]:
    with running_daemon(tmp_path, extra=["--config", str(FAST_CONFIG)]) as d:
        yield d


@pytest.fixture
def ui(tmp_path: Path, fast_daemon: Daemon) -> Iterator[UiServer]:
    with running_ui(tmp_path, fast_daemon) as server:
        yield server


@contextlib.contextmanager
def launched(*extra_args: str) -> Iterator[Any]:
    """Headless Chromium (Debian's), with `extra_args` after the usual ones."""
    sync_api = pytest.importorskip(
        "playwright.sync_api", reason="Playwright is not installed: pip install playwright"
    )
    exe = chromium_path()
    if exe is None:
        pytest.skip("no Chromium browser: apt-get install -y chromium (or set CHROMIUM=PATH)")
    with sync_api.sync_playwright() as p:
        b = p.chromium.launch(
            executable_path=exe, args=[*CHROMIUM_ARGS, *extra_args], timeout=60_000
        )
        try:
            yield b
        finally:
            b.close()


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    with launched() as b:
        yield b


@contextlib.contextmanager
def new_page(browser: Any, **context: Any) -> Iterator[Any]:
    """A page in a fresh context (`context`: Playwright's options, e.g. a viewport); any
    uncaught JavaScript error fails the test."""
    ctx = browser.new_context(**{"viewport": {"width": 1280, "height": 960}, **context})
    pg = ctx.new_page()
    errors: list[str] = []
    pg.on("pageerror", lambda exc: errors.append(str(exc)))
    try:
        yield pg
    finally:
        ctx.close()
    assert not errors, f"JavaScript errors on the page: {errors}"


PHONE = {"width": 390, "height": 844}
"""A common phone's viewport in CSS pixels (the layout must fit 360–414 px)."""


@pytest.fixture
def page(browser: Any) -> Iterator[Any]:
    with new_page(browser) as pg:
        yield pg


@pytest.fixture
def phone(browser: Any) -> Iterator[Any]:
    """A page as a phone shows it: 390 px wide, touch, the meta viewport honoured."""
    with new_page(
        browser, viewport=PHONE, is_mobile=True, has_touch=True, device_scale_factor=2
    ) as pg:
        yield pg


def shot(page: Any, name: str) -> Path:
    """Save a full-page screenshot under test-artifacts/ui/ (a CI artifact)."""
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    path = ARTIFACTS / f"{name}.png"
    page.screenshot(path=str(path), full_page=True)
    return path


def record(section: str, data: Any) -> Path:
    """Merge `data` under `section` into test-artifacts/ui/measured.json (for the notes)."""
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    path = ARTIFACTS / "measured.json"
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError):
        doc = {}
    doc[section] = data
    path.write_text(json.dumps(doc, indent=2, sort_keys=True) + "\n")
    return path
