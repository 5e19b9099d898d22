"""The machine daemon: typed IO, devices, controllers, the state machine, the scan loop, the bus."""

import sys

# The daemon and its history process hash with Python's own functions, not OpenSSL's: loading
# libcrypto (pydantic imports `secrets`, hence `hashlib`) costs 3.5 MiB resident per process,
# and nothing they run needs more than blake2b and the system's random numbers. `hashlib` and
# `hmac` fall back by design when `_hashlib` cannot be imported. A process that loaded it
# already (a test run, a library user) keeps it.
if "hashlib" not in sys.modules:
    sys.modules.setdefault("_hashlib", None)  # type: ignore[arg-type]
