"""`machine demo`: one whole session on the simulator in the terminal, no network needed.

The simulator is the HAL backend named `sim` (`hal.backends`), on a simulated clock."""

from __future__ import annotations

import logging
import time

from ride_machine.hal.backends import NoBackend, backend
from ride_machine.schema.commands import Command, CommandRequest, Reply, StartRequest
from ride_machine.schema.status import MachineState
from ride_machine.service.config.model import HalBackend, MachineConfig
from ride_machine.service.core.scan.machine import Machine
from ride_machine.service.core.scan.tasks import PendingCommand

log = logging.getLogger("demo")


class _SimClock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


class _Demo:
    """The machine on the simulator, stepped on a clock of its own."""

    def __init__(self, config: MachineConfig, speed: float, max_sim_s: float) -> None:
        self.clock = _SimClock()
        sim = backend(HalBackend.SIM)
        self.hal = sim.open(config.hal.iomap, config.hal.sim, self.clock, None)
        world = sim.simulator(self.hal)
        if world is None:
            raise NoBackend(f"the HAL backend {HalBackend.SIM.value!r} simulates nothing")
        self.world = world
        self.machine = Machine(config, self.hal, now=self.clock())
        self.loop, self.state_machine = self.machine.loop, self.machine.state_machine
        self.period = config.loop.period_s
        self.speed, self.max_sim_s = speed, max_sim_s
        self.replies: list[Reply] = []

    def send(self, command: Command) -> Reply:
        model = StartRequest if command is Command.START else CommandRequest
        self.loop.inbox.put(
            PendingCommand(
                command, model(transaction_id=f"demo-{command.key}"), self.replies.append
            )
        )
        self.loop.service_inbox(self.clock())
        reply = self.replies[-1]
        log.info(
            "event=reply command=%s success=%s code=%s state=%s",
            command,
            reply.success,
            reply.code,
            reply.state,
        )
        return reply

    def run_while(self, busy: set[MachineState]) -> None:
        clock = self.clock
        next_report = clock.t
        while self.state_machine.state in busy:
            if clock.t > self.max_sim_s:
                raise TimeoutError(f"demo did not finish within {self.max_sim_s} simulated seconds")
            clock.t += self.period
            self.loop.step(clock.t)
            if clock.t >= next_report:
                next_report += 1.0
                self._report()
            if self.speed > 0:
                time.sleep(self.period / self.speed)

    def _report(self) -> None:
        w = self.world.world(self.clock.t)
        log.info(
            "event=progress t=%.1f state=%s tilt_deg=%.1f rotate_deg=%.0f revolutions=%.2f",
            self.clock.t,
            self.state_machine.state,
            w.tilt_deg,
            w.rotate_deg,
            w.revolutions,
        )


def run_demo(config: MachineConfig, speed: float = 1.0, max_sim_s: float = 300.0) -> int:
    """Calibrate, home and run the default session; `speed` 0 means as fast as possible."""
    demo = _Demo(config, speed, max_sim_s)
    control, clock = demo.state_machine, demo.clock
    demo.loop.step(clock.t)
    motion = {MachineState.CALIBRATING, MachineState.HOMING, MachineState.RUNNING}
    for command in (Command.CALIBRATE_TILT, Command.CALIBRATE_ROTATE, Command.HOME, Command.START):
        if not demo.send(command).success:
            return 1
        demo.run_while(motion)
        if control.state is MachineState.FAULT_HW:
            log.error("event=fault detail=%r", control.fault)
            return 1
    progress = demo.loop.build_status(clock.t).session
    log.info("event=finished state=%s session=%s", control.state, progress)
    demo.hal.close()
    return 0 if control.state is MachineState.DONE else 1
