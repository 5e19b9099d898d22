"""The machine's state machine: read `table.py` first, it is what runs.

- `table`: the rows (trigger, states → targets), their vocabulary, the edges they allow;
- `guards`: what a row's `Pick` chooses and what refuses a command, from one `Facts` value;
- `machine`: `StateMachine`, which keeps the state, asks the table where each trigger leads
  and refuses any state change it does not have; its parts own the rest:
- `context`: the motion context (what a motion begins, its drive, its notices);
- `deadman`: the controlling Rider's watch; `calibration`: the calibration keeper;
- `handlers`: what each command asks for, as one value `StateMachine.handle` carries out;
- `snapshot`: the machine at one moment, as one frozen value compared with `==`.
"""

from .machine import StateMachine
from .snapshot import Snapshot
from .table import (
    HANDLING,
    TABLE,
    IllegalTransition,
    Occurrence,
    Rule,
    Transition,
    allowed_states,
    edges,
)

__all__ = [
    "HANDLING",
    "TABLE",
    "IllegalTransition",
    "Occurrence",
    "Rule",
    "Snapshot",
    "StateMachine",
    "Transition",
    "allowed_states",
    "edges",
]
