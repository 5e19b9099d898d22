"""The `rider` command's exit codes (what each means: rider/cli.py's docstring, `rider --help`)
and the usage error its sub-commands raise (exit 2)."""

from __future__ import annotations

EXIT_OK = 0
EXIT_REFUSED = 1
EXIT_USAGE = 2
EXIT_NO_REPLY = 3
EXIT_AMBIGUOUS = 4
EXIT_DUPLICATE = 5
EXIT_LINK_LOST = 6


class UsageError(Exception):
    """Bad arguments or an unreadable input file."""
