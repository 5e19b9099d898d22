"""glibc's malloc arenas, bounded on request (`loop.malloc_arenas`), so a daemon's memory
stays flat under heavy Rider connect churn.

glibc gives each thread that allocates its own arena, up to 8 per core. Zenoh's runtime and
the daemon's threads then spread the short-lived allocations of every Rider that connects
(the routes and declarations exchanged with a new peer) over many arenas, and the freed space
stays resident in each: RSS grew ~0.5 KiB per Rider connect after the first minutes, the
arenas' free space rising while the memory in use stayed flat (BENCHMARKS.md section 5). With
two arenas the same churn leaves RSS flat within the noise, at no measured cost in round trip,
but the scan's execution under motion load (publications every cycle from the scan thread,
Zenoh's threads allocating beside it) took 5-10 % longer at the median in six alternated
pairs: so it is an option, off by default.
"""

from __future__ import annotations

import ctypes
import os
import platform

MALLOC_ARENAS = 2
"""The cap that keeps RSS flat under churn: the main arena and one shared by every thread."""
M_ARENA_MAX = -8
"""`mallopt` parameter number, from glibc's <malloc.h>."""
ARENA_ENV = "MALLOC_ARENA_MAX"
TUNABLES_ENV = "GLIBC_TUNABLES"


def bound_malloc_arenas(limit: int | None = MALLOC_ARENAS) -> bool:
    """Cap this process's glibc malloc arenas at `limit` (None: leave glibc's, the
    `loop.malloc_arenas` default); whether a cap was applied.

    Call it before the process starts its threads (each takes an arena on its first
    allocation, up to the cap). Not applied on another C library, nor when the environment
    already sets the cap (`MALLOC_ARENA_MAX`, or `arena_max` in `GLIBC_TUNABLES`): glibc has
    applied that one at start-up, and the operator's choice wins.
    """
    if limit is None:
        return False
    if os.environ.get(ARENA_ENV) or "arena_max" in os.environ.get(TUNABLES_ENV, ""):
        return False
    if platform.libc_ver()[0] != "glibc":
        return False
    libc = ctypes.CDLL(None)  # the C library this process already runs on
    return bool(libc.mallopt(M_ARENA_MAX, limit))
