"""How `machine run` and `machine supervise` end: their exit codes, and a start refused."""

from __future__ import annotations

EXIT_OK = 0
EXIT_FAILED = 1
EXIT_CONFIG = 2
"""The config (or the IO map, or the HAL it names) is wrong: restarting would not help."""


class StartRefused(Exception):
    """A setup step found the daemon cannot run; what was set up so far is undone."""

    def __init__(self, code: int, reason: str) -> None:
        super().__init__(reason)
        self.code = code
        self.reason = reason
