"""Every baseline server stops on SIGTERM/SIGINT or at the end of its lifetime, whichever first."""

from __future__ import annotations

import signal
import threading
from types import FrameType


def stop_event(lifetime_s: float) -> threading.Event:
    """An event set by SIGTERM/SIGINT, or by a timer after `lifetime_s` (a bounded server)."""
    stop = threading.Event()

    def on_signal(signum: int, frame: FrameType | None) -> None:
        stop.set()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    timer = threading.Timer(lifetime_s, stop.set)
    timer.daemon = True
    timer.start()
    return stop
