"""Callbacks Zenoh runs on its own threads, which keep their Python thread state."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, TypeVar

import zenoh

from ride_machine.common.threadstate import keeping_state

T = TypeVar("T")


def direct(fn: Callable[[T], None]) -> zenoh.handlers.Callback[Any]:
    """`fn` run on Zenoh's own thread (no Python thread of its own, arrival order kept), with
    that thread's Python state kept between calls (`common.threadstate`: ~40 µs a call less).
    `fn` must never block."""
    return zenoh.handlers.Callback(keeping_state(fn), indirect=False)
