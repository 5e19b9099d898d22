"""The machine's state machine: read `table.py` first, it is what runs.

- `table`: the rows (trigger, states → targets), their vocabulary, the edges they allow;
- `machine`: `StateMachine`, which asks the table where each trigger leads and refuses any
  state change it does not have;
- `handlers`: one action per command; `context`: what a motion begins and leaves behind;
- `deadman`: the controlling Rider's watch; `calibration`: measured, entered, persisted;
- `snapshot`: the machine at one moment, as one frozen value compared with `==`.
"""

from service.core.statemachine.machine import StateMachine
from service.core.statemachine.snapshot import Snapshot
from service.core.statemachine.table import (
    HANDLING,
    TABLE,
    Event,
    IllegalTransition,
    Rule,
    Transition,
    allowed_states,
    edges,
)

__all__ = [
    "HANDLING",
    "TABLE",
    "Event",
    "IllegalTransition",
    "Rule",
    "Snapshot",
    "StateMachine",
    "Transition",
    "allowed_states",
    "edges",
]
