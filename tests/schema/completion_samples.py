"""A completion notice for tests: one motion that ended DONE, the rest as asked."""

from __future__ import annotations

from ride_machine.schema.completion import Completion, Outcome
from ride_machine.schema.status import MachineState


def done_notice(
    tid: str,
    command: str = "Start",
    state: MachineState = MachineState.DONE,
    *,
    started_at: float = 1.0,
    took_s: float = 1.0,
    rider: str | None = None,
) -> Completion:
    return Completion(
        machine_id="m1",
        transaction_id=tid,
        command=command,
        outcome=Outcome.DONE,
        state=state,
        rider=rider,
        started_at=started_at,
        time=started_at + took_s,
    )
