"""The `rider` command's sub-commands, by kind. Each parser (rider/subcommands/parsers.py)
carries its handler (`set_defaults(func=Lazy(kind, name))`); a handler runs on an open
`Rider` and returns the exit code (`handler(args, rider) -> int`, rider/exits.py). The handlers
live in one module per kind (reads, live, motion, settings), loaded only when one runs."""

from __future__ import annotations

import argparse
import importlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from ride_machine.rider.blocking import Rider

Subparsers = argparse._SubParsersAction
"""The type of what `add_subparsers()` returns (`Subparsers[argparse.ArgumentParser]`)."""

Handler = Callable[[argparse.Namespace, "Rider"], int]
"""A sub-command's handler: its parsed arguments and an open Rider in, the exit code out."""

KINDS = frozenset({"reads", "live", "motion", "settings"})


@dataclass(frozen=True)
class Lazy:
    """The handler `name` of module `rider.subcommands.<kind>`, imported when it is called: the
    client and the wire models load for a command that runs, not for `--help`."""

    kind: str
    name: str

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"no sub-command kind {self.kind!r}")

    def load(self) -> Handler:
        found: Handler = getattr(
            importlib.import_module(f"ride_machine.rider.subcommands.{self.kind}"), self.name
        )
        return found

    def __call__(self, args: argparse.Namespace, rider: Rider) -> int:
        return self.load()(args, rider)
