"""Strings from the wire, made safe to show: one line, no terminal control, no bidi tricks.

A machine (or anyone posing as one) chooses the session names, warnings and messages the
Rider prints. A newline would let it print a fake line (`state  IDLE`), an ESC could drive the
terminal, a NUL or U+202E (right-to-left override) could hide or reorder what follows. Every
character Python does not call printable is shown as its escape (`\\n`, `\\x1b`, `\\u202e`).
"""

from __future__ import annotations

from enum import Enum
from typing import Any, TypeVar

T = TypeVar("T")


def printable(text: str) -> str:
    """`text` unchanged when every character is printable; else with those escaped."""
    if text.isprintable():
        return text
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


def shown(value: T) -> T:
    """A copy of a wire model (or list, dict, str) with every string made `printable`."""
    from pydantic import BaseModel  # here, not above: `printable` alone loads no pydantic

    out: Any
    if isinstance(value, Enum):
        out = value  # our own names, and an enum member must stay one for comparisons
    elif isinstance(value, str):
        out = printable(value)
    elif isinstance(value, BaseModel):
        fields = type(value).model_fields
        out = value.model_copy(update={k: shown(getattr(value, k)) for k in fields})
    elif isinstance(value, list):
        out = [shown(v) for v in value]
    elif isinstance(value, tuple):
        out = tuple(shown(v) for v in value)
    elif isinstance(value, dict):
        out = {shown(k): shown(v) for k, v in value.items()}
    else:
        out = value
    return out  # type: ignore[no-any-return]
