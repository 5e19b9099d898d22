"""The `rider` command's exit codes (what each means: rider/cli.py's docstring, `rider --help`),
the usage error its sub-commands raise (exit 2), the exit code of each error (`EXITS`), and
the options of a sub-command that parses its own (`own_options`)."""

from __future__ import annotations

import argparse
import logging
from collections.abc import Sequence

from ride_machine.rider import errors

EXIT_OK = 0
EXIT_REFUSED = 1
EXIT_USAGE = 2
EXIT_NO_REPLY = 3
EXIT_AMBIGUOUS = 4
EXIT_DUPLICATE = 5
EXIT_LINK_LOST = 6


class UsageError(Exception):
    """Bad arguments or an unreadable input file."""


EXITS: tuple[tuple[type[Exception] | tuple[type[Exception], ...], int], ...] = (
    ((UsageError, errors.BadCredentials, errors.BadRuntime), EXIT_USAGE),
    (errors.CommandRefused, EXIT_REFUSED),
    (errors.AmbiguousMachine, EXIT_AMBIGUOUS),
    (errors.LinkLost, EXIT_LINK_LOST),
    (errors.DuplicateMachine, EXIT_DUPLICATE),
    ((errors.MachineTimeout, errors.NoMachine), EXIT_NO_REPLY),
    (errors.RiderError, EXIT_REFUSED),
)
"""The exit code of each error that ends a command (the first that matches)."""


def own_options(parser: argparse.ArgumentParser, argv: Sequence[str]) -> argparse.Namespace | int:
    """A sub-command that parses its own options (`rider ui`, `rider gateway`): its options,
    with logging set up at their `--log-level`; or the exit code argparse ended with (0 after
    `--help`, 2 for bad usage)."""
    try:
        args = parser.parse_args(list(argv))
    except SystemExit as exc:
        return EXIT_OK if exc.code == 0 else EXIT_USAGE
    logging.basicConfig(
        level=args.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s %(message)s"
    )
    return args
