"""`machine demo`: one whole session on the simulator in the terminal, no network needed.

The simulator is the HAL backend named `sim` (`hal.backends`), on a simulated clock."""

from __future__ import annotations

import logging
import time

from hal.backends import NoBackend, backend
from schema.commands import Command, CommandRequest, Reply, StartRequest
from schema.status import MachineState
from service.config.model import HalBackend, MachineConfig
from service.core.loop import PendingCommand
from service.core.machine import Machine

log = logging.getLogger("demo")


class _SimClock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def run_demo(config: MachineConfig, speed: float = 1.0, max_sim_s: float = 300.0) -> int:
    """Calibrate, home and run the default session; `speed` 0 means as fast as possible."""
    clock = _SimClock()
    sim = backend(HalBackend.SIM)
    hal = sim.open(config.hal.iomap, config.hal.sim, clock, None)
    world = sim.simulator(hal)
    if world is None:
        raise NoBackend(f"the HAL backend {HalBackend.SIM.value!r} simulates nothing")
    machine = Machine(config, hal, now=clock())
    loop, control = machine.loop, machine.control
    period = config.loop.period_s
    replies: list[Reply] = []

    def send(command: Command) -> Reply:
        model = StartRequest if command is Command.START else CommandRequest
        loop.inbox.put(
            PendingCommand(command, model(transaction_id=f"demo-{command.key}"), replies.append)
        )
        loop.service_inbox(clock())
        reply = replies[-1]
        log.info(
            "event=reply command=%s success=%s code=%s state=%s",
            command,
            reply.success,
            reply.code,
            reply.state,
        )
        return reply

    def run_while(busy: set[MachineState]) -> None:
        next_report = clock.t
        while control.state in busy:
            if clock.t > max_sim_s:
                raise TimeoutError(f"demo did not finish within {max_sim_s} simulated seconds")
            clock.t += period
            loop.step(clock.t)
            if clock.t >= next_report:
                next_report += 1.0
                w = world.world(clock.t)
                log.info(
                    "event=progress t=%.1f state=%s tilt_deg=%.1f rotate_deg=%.0f revolutions=%.2f",
                    clock.t,
                    control.state,
                    w.tilt_deg,
                    w.rotate_deg,
                    w.revolutions,
                )
            if speed > 0:
                time.sleep(period / speed)

    loop.step(clock.t)
    motion = {MachineState.CALIBRATING, MachineState.HOMING, MachineState.RUNNING}
    for command in (Command.CALIBRATE_TILT, Command.CALIBRATE_ROTATE, Command.HOME, Command.START):
        if not send(command).success:
            return 1
        run_while(motion)
        if control.state is MachineState.FAULT_HW:
            log.error("event=fault detail=%r", control.fault)
            return 1
    progress = loop.build_status(clock.t).session
    log.info("event=finished state=%s session=%s", control.state, progress)
    hal.close()
    return 0 if control.state is MachineState.DONE else 1
