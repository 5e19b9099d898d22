"""The `rider` command's sub-commands, by kind. Each `add_<name>(sub)` adds one sub-command's
parser, which carries its handler (`set_defaults(func=handler)`); a handler runs on an open
`Rider` and returns the exit code (`handler(args, rider) -> int`, rider/exits.py)."""

from __future__ import annotations

import argparse
from collections.abc import Callable

from rider.blocking import Rider

Subparsers = argparse._SubParsersAction
"""The type of what `add_subparsers()` returns (`Subparsers[argparse.ArgumentParser]`)."""

Handler = Callable[[argparse.Namespace, Rider], int]
"""A sub-command's handler: its parsed arguments and an open Rider in, the exit code out."""
