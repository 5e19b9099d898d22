"""Wait until the operator UI shows a machine state, reading its event stream like a browser.

    python -m tests.deploy.ui_probe http://127.0.0.1:8080 DONE --timeout 20

Exit 0 when the UI's `snapshot` or a `status` event carries that state, 1 when the deadline
passes first (the UI's keep-alive ticks bound every read), 2 when the UI cannot be reached.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import urllib.request
from collections.abc import Iterator, Sequence
from typing import Any


def events(url: str, timeout: float) -> Iterator[tuple[str, Any]]:
    """(event, data) from a server-sent event stream."""
    with urllib.request.urlopen(f"{url}/api/events", timeout=timeout) as stream:
        kind = ""
        for raw in stream:
            line = raw.decode().rstrip("\n")
            if line.startswith("event: "):
                kind = line[len("event: ") :]
            elif line.startswith("data: "):
                yield kind, json.loads(line[len("data: ") :])


def state_of(kind: str, data: Any) -> str | None:
    if kind == "snapshot" and data.get("status"):
        return str(data["status"]["state"])
    if kind == "status":
        return str(data["state"])
    return None


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="ui_probe", description=__doc__)
    p.add_argument("url")
    p.add_argument("state")
    p.add_argument("--timeout", type=float, default=20.0)
    args = p.parse_args(argv)
    deadline = time.monotonic() + args.timeout
    seen: list[str] = []
    try:
        for kind, data in events(args.url, timeout=args.timeout):
            state = state_of(kind, data)
            if state is not None:
                seen.append(state)
            if state == args.state:
                print(json.dumps({"state": state, "seen": seen}))
                return 0
            if time.monotonic() > deadline:
                break
    except OSError as exc:
        print(f"ui_probe: {args.url}: {exc}", file=sys.stderr)
        return 2
    print(f"ui_probe: no {args.state} within {args.timeout:g} s (seen {seen})", file=sys.stderr)
    return 1


if __name__ == "__main__":
    sys.exit(main())
