"""What `rider … --wait` says while it waits for a motion's completion notice.

Through a link that stalled mid-session the machine paused in 0.6 s, correctly, and the CLI
showed RUNNING and said nothing for 33 s. Now, on stderr:

- once the machine (or the link to it) has been silent for `quiet_limit` (the Rider's
  `--timeout`, or 2.5 status heartbeats when they are slower), and whether this session has
  any link left at all;
- when it is heard again, in the state it is in, and once when the awaited motion is paused
  or E-stopped, with the machine's reason (e.g. its controlling Rider was lost: the deadman
  paused it while the link was down);
- and the wait ends with `LINK_LOST_EXIT` (`LinkLost`) once it has heard nothing for
  `--link-limit` seconds, rather than waiting out `--wait-timeout` in the dark.
"""

from __future__ import annotations

import sys
from collections.abc import Callable

from ride_machine.schema.status import MachineState, Status

from .text import printable


def tell(text: str) -> None:
    print(f"rider: {printable(text)}", file=sys.stderr, flush=True)


class WaitTeller:
    """What `--wait` says on stderr while it waits (see the module's docstring)."""

    def __init__(self, machine_id: str, link: Callable[[], str] = lambda: "") -> None:
        """`link`: "" while this session has a link to a Zenoh node, else why it has none."""
        self.machine_id = machine_id
        self.link = link
        self.said: MachineState | None = None
        self.silent = False
        self.last: MachineState | None = None

    def on_status(self, status: Status) -> None:
        if self.silent:
            self.silent = False
            tell(f"machine {self.machine_id} answering again: {status.state}")
        self.last = status.state
        if status.state in (MachineState.PAUSED, MachineState.FAULT_ESTOP):
            if self.said is not status.state:
                self.said = status.state
                why = f" ({'; '.join(status.warnings)})" if status.warnings else ""
                tell(
                    f"machine {status.state}{why}; the motion continues after resume (stop ends it)"
                )
        else:
            self.said = None

    def on_silence(self, quiet_s: float) -> None:
        self.silent = True
        last = f" (last heard: {self.last})" if self.last is not None else ""
        down = self.link()
        cause = f"the link is down{down}" if down else "frozen, overloaded or the link is down"
        tell(
            f"machine {self.machine_id} not answering for {quiet_s:.1f} s{last}: {cause};"
            " still waiting (Ctrl-C stops waiting, not the ride)"
        )


class Silence:
    """How long the machine has been silent: told once per silence (`on_silence`, after
    `quiet_s`), and past `limit` the wait gives up (`check` says how long it lasted)."""

    def __init__(
        self,
        quiet_s: float,
        on_silence: Callable[[float], None] | None,
        limit: float | None,
        now: float,
    ) -> None:
        self.quiet_s = quiet_s
        self.on_silence = on_silence
        self.limit = limit
        self._at = now
        self._told = False

    def heard(self, now: float) -> None:
        self._at, self._told = now, False

    def check(self, now: float) -> float | None:
        """The silence's length once it is past `limit` (None: not yet, or no limit)."""
        quiet = now - self._at
        if self.on_silence is not None and not self._told and quiet > self.quiet_s:
            self._told = True
            self.on_silence(quiet)
        return quiet if self.limit is not None and quiet > self.limit else None


def quiet_limit(timeout: float, heartbeat_s: float) -> float:
    """How long `--wait` hears nothing before it says so: the Rider's timeout, or 2.5 of the
    machine's status heartbeats when they are slower (an idle machine is quiet in between)."""
    return max(timeout, 2.5 * heartbeat_s)
