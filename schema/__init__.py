"""Wire models of every message between the machine daemon and its Riders, and their codec."""

from __future__ import annotations

SCHEMA_VERSION = 2
"""Bumped only for incompatible changes; new optional fields keep the version.

2: a supervising Rider's keys are `rider/<login>/<zid>/…` and its id `<login>/<zid>`
(schema/rider.py; a motion command naming a schema-1 id is refused), and a motion command's
`timecode` that is not seconds, or is ahead of the machine's clock, is refused `BAD_TIMECODE`."""
