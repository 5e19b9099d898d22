"""A TCP link that a test can stall and cut: `python -m tests.linkproxy PORT TARGET_PORT`.

It listens on 127.0.0.1:PORT and joins each connection to 127.0.0.1:TARGET_PORT, a thread per
direction. SIGSTOP stalls the link (nothing moves; the kernel still accepts new connections
into the backlog), SIGCONT lets it go on, SIGKILL cuts it (both ends reset, the port refuses).
Prints `ready` once it listens.
"""

from __future__ import annotations

import contextlib
import socket
import subprocess
import sys
import threading

BUFFER = 65536


def pump(src: socket.socket, dst: socket.socket) -> None:
    """Bytes one way until either end closes; then both are closed."""
    try:
        while data := src.recv(BUFFER):
            dst.sendall(data)
    except OSError:
        pass
    finally:
        for s in (src, dst):
            with contextlib.suppress(OSError):
                s.shutdown(socket.SHUT_RDWR)
            s.close()


def main(argv: list[str]) -> int:
    port, target = int(argv[0]), int(argv[1])
    server = socket.create_server(("127.0.0.1", port), reuse_port=False)
    print("ready", flush=True)
    while True:
        client, _ = server.accept()
        try:
            upstream = socket.create_connection(("127.0.0.1", target), timeout=5.0)
        except OSError:
            client.close()
            continue
        upstream.settimeout(None)
        for a, b in ((client, upstream), (upstream, client)):
            threading.Thread(target=pump, args=(a, b), daemon=True).start()


def start(port: int, target: str, timeout: float = 30.0) -> subprocess.Popen[str]:
    """This proxy in a process of its own, on `port` to 127.0.0.1:`target`, once it listens."""
    from tests.procs import REPO, LineReader

    link = subprocess.Popen(
        [sys.executable, "-m", "tests.linkproxy", str(port), target],
        stdout=subprocess.PIPE,
        text=True,
        cwd=REPO,
    )
    assert link.stdout is not None
    assert LineReader(link.stdout).line(timeout) == "ready"
    return link


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
