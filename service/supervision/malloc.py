"""glibc's malloc arenas, bounded, so a long-running daemon's memory stays flat.

glibc gives each thread that allocates its own arena, up to 8 per core. Zenoh's runtime and
the daemon's threads then spread the short-lived allocations of every Rider that connects
(the routes and declarations exchanged with a new peer) over many arenas, and the freed space
stays resident in each: RSS grew ~0.5 KiB per Rider connect after the first minutes, the
arenas' free space rising while the memory in use stayed flat (BENCHMARKS.md section 5). With
two arenas the same churn leaves RSS flat within the noise, at no measured cost in round trip.
"""

from __future__ import annotations

import ctypes
import os
import platform

MALLOC_ARENAS = 2
"""The arenas a daemon process allocates from: the main one and one shared by its threads."""
M_ARENA_MAX = -8
"""`mallopt` parameter number, from glibc's <malloc.h>."""
ARENA_ENV = "MALLOC_ARENA_MAX"
TUNABLES_ENV = "GLIBC_TUNABLES"


def bound_malloc_arenas(limit: int = MALLOC_ARENAS) -> bool:
    """Cap this process's glibc malloc arenas at `limit`; whether it was applied.

    Call it before the process starts its threads (each takes an arena on its first
    allocation, up to the cap). Not applied on another C library, nor when the environment
    already sets the cap (`MALLOC_ARENA_MAX`, or `arena_max` in `GLIBC_TUNABLES`): glibc has
    applied that one at start-up, and the operator's choice wins.
    """
    if os.environ.get(ARENA_ENV) or "arena_max" in os.environ.get(TUNABLES_ENV, ""):
        return False
    if platform.libc_ver()[0] != "glibc":
        return False
    libc = ctypes.CDLL(None)  # the C library this process already runs on
    return bool(libc.mallopt(M_ARENA_MAX, limit))
