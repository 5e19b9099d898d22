"""The machine link as `rider ui` judges it follows the machine's own status heartbeat
(`bus.heartbeat_s`, up to 60 s): a machine at rest that publishes its status every 2 s is
live, not "reconnecting" for half a second of every two."""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from tests.procs import Daemon
from tests.ui.uiproc import UiServer, events, request, running_ui

pytestmark = pytest.mark.integration

HEARTBEAT_S = 2.0
GAPS = 2
"""Heartbeat gaps watched: the old fixed 1.5 s limit called the link lost in each."""


def link_drops(ui: UiServer, watch_s: float) -> tuple[list[str], int]:
    """The reasons of every link loss the event stream tells in `watch_s`, and the statuses."""
    drops: list[str] = []
    statuses = 0
    until = time.monotonic() + watch_s
    for kind, data in events(ui.port):
        link = data["link"] if kind == "snapshot" else data
        if kind in ("snapshot", "link") and not link["up"]:
            drops.append(link["reason"])
        statuses += kind == "status"
        if time.monotonic() > until:  # a tick or a sample comes every 0.5 s at most
            break
    return drops, statuses


def test_a_slower_heartbeat_set_while_the_page_is_open_is_followed(
    ui: UiServer, fast_daemon: Daemon
) -> None:
    done = fast_daemon.cli("params", "set", "bus.heartbeat_s", str(HEARTBEAT_S))
    assert done.returncode == 0, done.stderr
    drops, statuses = link_drops(ui, GAPS * HEARTBEAT_S + 0.5)
    assert statuses >= GAPS - 1  # the machine did publish: the heartbeats, 2 s apart
    assert not drops, drops
    _, snap = request(ui.port, "GET", "/api/snapshot")
    assert snap["link"]["up"], snap["link"]


def test_a_ui_started_on_a_slow_heartbeat_reads_it_first(
    tmp_path: Path, fast_daemon: Daemon
) -> None:
    done = fast_daemon.cli("params", "set", "bus.heartbeat_s", str(HEARTBEAT_S))
    assert done.returncode == 0, done.stderr
    with running_ui(tmp_path, fast_daemon) as ui:
        drops, _ = link_drops(ui, GAPS * HEARTBEAT_S + 0.5)
    assert not drops, drops
