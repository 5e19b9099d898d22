"""The simulated plant as a process of its own: the ride's world behind a process image, on its
own clock, as a real machine stands beside its PLC.

`machine supervise --sim` starts it as a child (`sim.plant_link`); nothing that stops the
controller's processes — SIGSTOP of the supervisor and the daemon, a cgroup freezer, a hung
interpreter — stops this clock, so a freeze of the whole controller is measured as a ride would
live it: the charge pump stops toggling and the external relay cuts the drives.

    python -m ride_machine.sim.plant --dir DIR --config FILE [--socket PATH] [--period S] [--parent
    PID]
                        [--beat-fd FD --beat-offset N] [--make-image]

DIR gets the process image (`procimg`, made by whoever starts the plant, or by the plant with
`--make-image`: a compose service of its own, docker/compose.plant.yaml) and the control socket
(`plant.sock`, or `--socket PATH`; the file `plant.endpoint` names it); FILE is a TOML or JSON
document whose `hal.iomap` and `hal.sim` tables wire and shape the world (a machine.toml does).
The world steps every S seconds; the plant asks for real-time scheduling for all its threads
(the field's physics is never late; refused, it runs as any process and counts its late steps).
`--beat-fd`: the daemon's scan count, a uint64 at offset N of that shared memory, so the rotate
waits in its home arc for a stalled scan (`SimWorld.follow_scans`). It prints `ready` once the
socket listens and stops on SIGTERM, SIGINT, a `stop` request, or when its parent (`--parent`)
is gone.
"""

from __future__ import annotations

import argparse
import json
import logging
import mmap
import os
import signal
import socket
import struct
import sys
import threading
import tomllib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import msgpack

from ride_machine.hal.iomap import IoMap
from ride_machine.schema.sim import SIM_REQUESTS

from .settings import PhysicsParams
from .world import CONFIG_RSC, SimWorld, make_image

log = logging.getLogger("plant")

SOCKET = "plant.sock"
ENDPOINT = "plant.endpoint"
"""A file in the plant's directory that names its socket (a socket's path is at most 107
bytes: a deep directory gets one in a short temporary folder, `--socket`)."""
IMAGE = "procimg"
PERIOD_S = 0.005
RT_PRIORITY = 10
"""SCHED_FIFO priority of the world's thread: above every normal thread, below the kernel's."""
_HEADER = struct.Struct("!I")
MAX_FRAME = 1 << 20


def send_frame(sock: socket.socket, value: object) -> None:
    """One msgpack value, length first."""
    body = msgpack.packb(value, use_bin_type=True)
    sock.sendall(_HEADER.pack(len(body)) + body)


def recv_frame(sock: socket.socket) -> Any:
    """One msgpack value; EOFError when the other side closed."""
    (size,) = _HEADER.unpack(_recv_exactly(sock, _HEADER.size))
    if size > MAX_FRAME:
        raise ValueError(f"a frame of {size} bytes is more than {MAX_FRAME}")
    return msgpack.unpackb(_recv_exactly(sock, size), raw=False)


def _recv_exactly(sock: socket.socket, n: int) -> bytes:
    chunks, left = [], n
    while left:
        chunk = sock.recv(left)
        if not chunk:
            raise EOFError("closed")
        chunks.append(chunk)
        left -= len(chunk)
    return b"".join(chunks)


def read_tables(path: Path) -> tuple[IoMap, PhysicsParams]:
    """The world's wiring and mechanics: `hal.iomap` and `hal.sim` of a TOML or JSON file."""
    text = path.read_bytes()
    doc = json.loads(text) if path.suffix == ".json" else tomllib.loads(text.decode())
    hal = doc.get("hal", {})
    return IoMap.model_validate(hal.get("iomap", {})), PhysicsParams.model_validate(
        hal.get("sim", {})
    )


def realtime() -> bool:
    """The calling thread, and every thread it starts from now on, real-time (SCHED_FIFO): the
    field is never late, and no thread of the plant waits behind a busy neighbour for the GIL
    another of its threads holds. False where the host refuses (late steps are counted)."""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(RT_PRIORITY))
    except (PermissionError, OSError) as exc:
        log.warning("event=plant_not_realtime error=%r (late steps are counted)", str(exc))
        return False
    return True


def beat_counter(fd: int, offset: int) -> Callable[[], int]:
    """The daemon's completed scans: a uint64 at `offset` of the shared memory `fd`."""
    view = mmap.mmap(fd, mmap.PAGESIZE, mmap.MAP_SHARED, mmap.PROT_READ)
    return lambda: int.from_bytes(view[offset : offset + 8], sys.byteorder)


class Plant:
    """The world and the control socket that serves it (one thread per connection)."""

    def __init__(self, world: SimWorld, directory: Path, path: Path | None = None) -> None:
        self.world = world
        self.stopped = threading.Event()
        path = path or directory / SOCKET
        path.unlink(missing_ok=True)
        self.server = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self.server.bind(str(path))
        self.server.listen(8)
        (directory / ENDPOINT).write_text(str(path))

    def serve(self) -> None:
        threading.Thread(target=self._accept, name="plant-accept", daemon=True).start()

    def _accept(self) -> None:
        while not self.stopped.is_set():
            try:
                conn, _ = self.server.accept()
            except OSError:
                return
            threading.Thread(target=self._serve, args=(conn,), daemon=True).start()

    def _serve(self, conn: socket.socket) -> None:
        with conn:
            while True:
                try:
                    request = recv_frame(conn)
                except (EOFError, OSError, ValueError):
                    return
                send_frame(conn, self.answer(request))

    def answer(self, request: dict[str, Any]) -> dict[str, Any]:
        """One request: `{"ok": value}`, or `{"error": why}` (nothing changed)."""
        op = request.get("op") if isinstance(request, dict) else None
        try:
            if op == "world":
                return {"ok": self.world.world(float(request["stamp"])).model_dump(mode="json")}
            if op == "apply":
                model = SIM_REQUESTS[str(request["what"])]
                self.world.apply(model.model_validate(request["request"]))
                return {"ok": None}
            if op == "step_now":
                self.world.step_now()
                return {"ok": None}
            if op == "stop":
                self.stopped.set()
                return {"ok": None}
        except (KeyError, TypeError, ValueError) as exc:  # pydantic's errors are ValueErrors
            return {"error": f"{op}: {exc}"}
        return {"error": f"unknown request {op!r}"}

    def close(self) -> None:
        self.stopped.set()
        self.server.close()


def parse(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="python -m ride_machine.sim.plant", description=__doc__)
    p.add_argument("--dir", type=Path, required=True)
    p.add_argument("--config", type=Path, required=True)
    p.add_argument("--socket", type=Path, default=None, help="(default: DIR/plant.sock)")
    p.add_argument("--period", type=float, default=PERIOD_S)
    p.add_argument("--parent", type=int, default=None)
    p.add_argument("--beat-fd", type=int, default=None)
    p.add_argument("--beat-offset", type=int, default=0)
    p.add_argument(
        "--make-image",
        action="store_true",
        help="make DIR/procimg itself (a plant started on its own, e.g. a compose service)",
    )
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(message)s")
    sys.setswitchinterval(0.0005)  # a request's thread must not keep the world waiting
    iomap, params = read_tables(args.config)
    image = args.dir / IMAGE
    if args.make_image:
        args.dir.mkdir(parents=True, exist_ok=True)
        make_image(image)
    rt = realtime()  # before any thread starts: they inherit it
    world = SimWorld(iomap, str(image), str(CONFIG_RSC), params, args.period)
    if args.beat_fd is not None:
        world.follow_scans(beat_counter(args.beat_fd, args.beat_offset))
    plant = Plant(world, args.dir, args.socket)
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: plant.stopped.set())
    world.start()
    plant.serve()
    log.info(
        "event=plant_started dir=%s period_s=%g pump=%s realtime=%s",
        args.dir,
        args.period,
        iomap.charge_pump or "none",
        rt,
    )
    print("ready", flush=True)
    try:
        while not plant.stopped.wait(1.0):
            if args.parent is not None and os.getppid() != args.parent:
                log.warning("event=plant_orphaned parent=%d", args.parent)
                break
    finally:
        plant.close()
        world.stop()
        log.info("event=plant_stopped late_steps=%d", world.late_steps)
    return 0


if __name__ == "__main__":
    sys.exit(main())
