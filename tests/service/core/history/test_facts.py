"""A command's facts make the event the history writes: `details()` (no pydantic, the history
process's) is the text the model's serializer writes of the `CommandEvent` they make."""

from __future__ import annotations

from hypothesis import given
from hypothesis import strategies as st

from ride_machine.schema.codec import dump_json
from ride_machine.schema.status import MachineState
from ride_machine.service.core.history.facts import CommandFacts

# Any text: quotes, backslashes, control characters, non-ASCII (no lone surrogates: the wire
# refuses them before a command is answered).
TEXT = st.text(st.characters(exclude_categories=("Cs",)), max_size=40)
MAYBE = st.none() | TEXT

FACTS = st.builds(
    CommandFacts,
    command=TEXT,
    transaction_id=TEXT,
    rider=MAYBE,
    accepted=st.booleans(),
    code=TEXT,
    message=TEXT,
    state=st.none() | st.sampled_from([s.value for s in MachineState]),
    repeat=st.booleans(),
    timecode=st.none() | st.floats(allow_nan=False),
    identity=MAYBE,
    operator=MAYBE,
)


@given(FACTS)
def test_a_commands_details_without_the_model_are_the_models_text(facts: CommandFacts) -> None:
    assert facts.details() == dump_json(facts())


def test_the_details_escape_what_json_escapes_as_the_model_does() -> None:
    text = "".join(chr(i) for i in range(0x80)) + 'é€😀\u2028\u2029\x85"\\'
    facts = CommandFacts(text, text, text, False, text, text, "RUNNING", True, 1.5, text, text)
    assert facts.details() == dump_json(facts())
