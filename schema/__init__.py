"""Wire models of every message between the machine daemon and its Riders, and their codec."""

from __future__ import annotations

SCHEMA_VERSION = 1
"""Bumped only for incompatible changes; new optional fields keep the version."""
