"""gRPC unary echo over a Unix domain socket (the original design's transport).

The service is defined with grpc's generic handlers on raw bytes, so no protoc codegen is needed.
"""

from __future__ import annotations

import argparse
import sys
from concurrent import futures

import grpc

from bench.baselines.lifetime import stop_event

METHOD = "/bench.Echo/Call"


def _echo(request: bytes, context: grpc.ServicerContext) -> bytes:
    return request


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--socket", required=True, help="path of the Unix socket to create")
    parser.add_argument("--lifetime", type=float, default=600.0, help="exit after this many s")
    args = parser.parse_args(argv)
    stop = stop_event(args.lifetime)
    server = grpc.server(futures.ThreadPoolExecutor(max_workers=4))
    handler = grpc.method_handlers_generic_handler(
        "bench.Echo", {"Call": grpc.unary_unary_rpc_method_handler(_echo)}
    )
    server.add_generic_rpc_handlers((handler,))
    server.add_insecure_port(f"unix:{args.socket}")
    server.start()
    print(f"ready {args.socket}", flush=True)
    stop.wait()
    server.stop(grace=1.0).wait(5.0)
    return 0


class GrpcClient:
    """A channel to the echo server; `call(payload)` is one unary RPC."""

    def __init__(self, socket_path: str, timeout: float = 2.0) -> None:
        self.channel = grpc.insecure_channel(f"unix:{socket_path}")
        self.stub = self.channel.unary_unary(METHOD)
        self.timeout = timeout

    def call(self, payload: bytes) -> bytes:
        reply: bytes = self.stub(payload, timeout=self.timeout)
        return reply

    def close(self) -> None:
        self.channel.close()


if __name__ == "__main__":
    sys.exit(main())
