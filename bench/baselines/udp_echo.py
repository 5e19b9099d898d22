"""A raw UDP echo server on loopback: the floor for a Python request/response."""

from __future__ import annotations

import argparse
import socket
import sys

from bench.baselines.lifetime import stop_event


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--lifetime", type=float, default=600.0, help="exit after this many s")
    args = parser.parse_args(argv)
    stop = stop_event(args.lifetime)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))
        sock.settimeout(0.2)  # so the stop event is seen while idle
        print(f"ready {sock.getsockname()[1]}", flush=True)
        while not stop.is_set():
            try:
                data, peer = sock.recvfrom(65536)
            except TimeoutError:
                continue
            sock.sendto(data, peer)
    return 0


class UdpClient:
    """A connected UDP socket: `call(payload)` sends and waits for the echo."""

    def __init__(self, port: int, timeout: float = 2.0) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.connect(("127.0.0.1", port))
        self.sock.settimeout(timeout)

    def call(self, payload: bytes) -> bytes:
        self.sock.send(payload)
        return self.sock.recv(65536)

    def close(self) -> None:
        self.sock.close()


if __name__ == "__main__":
    sys.exit(main())
