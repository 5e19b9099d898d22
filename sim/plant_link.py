"""The supervisor's side of the simulated plant (`sim.plant`): `hal.backends.World` over a child
process and its control socket.

The supervisor makes the process image, starts the plant on it, drives it with the RevPi
backend like real hardware, and asks it for faults and for the truth (`sim/<fault>`,
`sim/world`) through the socket. The plant keeps its own clock: SIGSTOP of the supervisor and
its daemon, or a cgroup freezer around them, leaves it running.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import select
import shutil
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

from pydantic import BaseModel

from ride_machine.hal.base import HalError
from ride_machine.hal.iomap import IoMap
from ride_machine.schema.sim import SIM_REQUESTS, SimWorldState
from ride_machine.sim import faults as simfaults

from .plant import ENDPOINT, IMAGE, SOCKET, recv_frame, send_frame
from .settings import PhysicsParams
from .world import CONFIG_RSC, make_image

log = logging.getLogger(__name__)

START_TIMEOUT_S = 30.0
CALL_TIMEOUT_S = 0.5
"""A plant that does not answer within this is treated as gone (a request fails). Short: the
supervisor asks on a Zenoh callback thread (`sim/*`) and from its output guard, neither of which
may wait long; the plant answers in well under a millisecond (it runs real-time)."""
STOP_TIMEOUT_S = 5.0


class PlantProcess:
    """The plant as a child process: `start()` runs `python -m ride_machine.sim.plant` on a fresh
    process image in `directory`; every other call is one request over its socket. `attach`: a plant
    someone else runs in `directory` (a compose service of its own), found, never stopped."""

    def __init__(
        self,
        iomap: IoMap,
        params: PhysicsParams,
        directory: Path,
        period_s: float,
        *,
        attach: bool = False,
    ) -> None:
        self.dir = directory
        self.attach = attach
        self.procimg = str(directory / IMAGE) if attach else make_image(directory / IMAGE)
        self.configrsc = str(CONFIG_RSC)
        self.period = period_s
        self._config = directory / "plant.json"
        if not attach:
            tables = {"iomap": iomap.model_dump(by_alias=True), "sim": params.model_dump()}
            self._config.write_text(json.dumps({"hal": tables}))
        self._sockdir = Path(tempfile.mkdtemp(prefix="plant-"))  # short: at most 107 bytes
        self.socket = self._sockdir / SOCKET
        self._beat: tuple[int, int] | None = None
        self._proc: subprocess.Popen[str] | None = None
        self._sock: socket.socket | None = None
        self._lock = threading.Lock()

    @property
    def pid(self) -> int | None:
        """The plant's process id, once started."""
        return None if self._proc is None else self._proc.pid

    def follow_beat(self, fd: int, offset: int) -> None:
        """The daemon's scan count at `offset` of the shared memory `fd`: the plant holds the
        rotate in its home arc for a scan that stalled there (`SimWorld.follow_scans`)."""
        self._beat = (fd, offset)

    def start(self) -> None:
        if self.attach:
            self._find()
            return
        cmd = [sys.executable, "-m", "ride_machine.sim.plant", "--dir", str(self.dir), "--config"]
        cmd += [str(self._config), "--socket", str(self.socket), "--period", str(self.period)]
        cmd += ["--parent", str(os.getpid())]
        fds: tuple[int, ...] = ()
        if self._beat is not None:
            cmd += ["--beat-fd", str(self._beat[0]), "--beat-offset", str(self._beat[1])]
            fds = (self._beat[0],)
        self._proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True, pass_fds=fds)
        self._wait_ready(self._proc)
        log.info("event=plant_up pid=%d dir=%s", self._proc.pid, self.dir)

    def _find(self) -> None:
        """A plant someone else started: its socket, once it names one and the image is there
        (bounded). Its beat record cannot reach another container: no arc hold then."""
        deadline = time.monotonic() + START_TIMEOUT_S
        endpoint = self.dir / ENDPOINT
        while True:  # an endpoint left by an earlier plant names a socket nobody answers on
            try:
                self.socket = Path(endpoint.read_text())
                Path(self.procimg).stat()
                self._call({"op": "world", "stamp": 0.0})
                break
            except (OSError, HalError) as exc:
                if time.monotonic() > deadline:
                    raise HalError(f"no simulated plant answers in {self.dir}: {exc}") from exc
            time.sleep(0.05)
        log.info("event=plant_found dir=%s socket=%s", self.dir, self.socket)

    def _wait_ready(self, proc: subprocess.Popen[str]) -> None:
        assert proc.stdout is not None
        ready, _, _ = select.select([proc.stdout], [], [], START_TIMEOUT_S)
        line = proc.stdout.readline() if ready else ""
        if line.strip() != "ready":
            proc.kill()
            proc.wait(timeout=STOP_TIMEOUT_S)
            raise HalError(f"the simulated plant did not start (it said {line.strip()!r})")

    def stop(self) -> None:
        proc = self._proc
        if proc is None:  # not started, or attached: the plant is not ours to stop
            if self._sock is not None:
                self._sock.close()
            shutil.rmtree(self._sockdir, ignore_errors=True)
            return
        with contextlib.suppress(HalError):
            self._call({"op": "stop"})
        try:
            proc.wait(timeout=STOP_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=STOP_TIMEOUT_S)
        if self._sock is not None:
            self._sock.close()
        shutil.rmtree(self._sockdir, ignore_errors=True)

    def step_now(self) -> None:
        """One step at once, so the plant has seen outputs just dropped: asked from the output
        guard's thread, which must go on whatever the plant does, so a failure is logged, never
        raised (the plant sees the image at its next step anyway, 5 ms on)."""
        try:
            self._call({"op": "step_now"})
        except HalError as exc:
            log.warning("event=plant_step_failed error=%r", str(exc))

    def decode(self, what: str, payload: bytes, encoding: str | None) -> BaseModel:
        return simfaults.decode_request(what, payload, encoding)

    def apply(self, request: BaseModel) -> None:
        what = next(k for k, model in SIM_REQUESTS.items() if isinstance(request, model))
        self._call({"op": "apply", "what": what, "request": request.model_dump(mode="json")})

    def world(self, stamp: float) -> SimWorldState:
        return SimWorldState.model_validate(self._call({"op": "world", "stamp": stamp}))

    def _call(self, request: dict[str, Any]) -> Any:
        """One request and its answer, on the one connection (made again once if it broke)."""
        with self._lock:
            for attempt in (1, 2):
                try:
                    sock = self._connected()
                    send_frame(sock, request)
                    answer = recv_frame(sock)
                    break
                except (OSError, EOFError, ValueError) as exc:
                    if self._sock is not None:
                        self._sock.close()
                    self._sock = None
                    # Once more only for a connection that broke, never after a wait that ran out.
                    if attempt == 2 or isinstance(exc, TimeoutError):
                        raise HalError(f"the simulated plant did not answer: {exc}") from exc
        if "error" in answer:
            raise HalError(f"the simulated plant refused {request['op']}: {answer['error']}")
        return answer.get("ok")

    def _connected(self) -> socket.socket:
        if self._sock is None:
            sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            sock.settimeout(CALL_TIMEOUT_S)
            sock.connect(str(self.socket))
            self._sock = sock
        return self._sock
