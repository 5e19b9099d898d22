"""Wire strings made safe to print: escapes for everything not printable, nothing else."""

from __future__ import annotations

from ride_machine.rider.text import printable, shown
from ride_machine.schema.status import MachineState, SessionProgress, Status


def test_printable_escapes_control_format_and_bidi_characters() -> None:
    assert printable("ride 1 °") == "ride 1 °"
    assert printable("a\nb\x1b[2J\x00\u202ec\t") == "a\\nb\\x1b[2J\\x00\\u202ec\\t"


def test_shown_escapes_every_string_in_a_model_and_keeps_enums() -> None:
    status = Status(
        machine_id="m1",
        state=MachineState.IDLE,
        session=SessionProgress(name="x\ny", step_index=0, step_count=1),
        warnings=["w\x1b"],
        seq=1,
        cycle=1,
        time=0.0,
    )
    safe = shown(status)
    assert safe.state is MachineState.IDLE
    assert safe.session is not None and safe.session.name == "x\\ny"
    assert safe.warnings == ["w\\x1b"]
    assert status.warnings == ["w\x1b"]  # the original is untouched
