"""The machine's change count, kept in one place: a method that may change what the machine's
snapshot shows is marked `@acts` and counts each call, first, whatever it then does. The scan
loop's quiet cycles compare the count (service/core/loop.py)."""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Concatenate, ParamSpec, Protocol, TypeVar


class Counted(Protocol):
    """What keeps a change count."""

    changes: int


P = ParamSpec("P")
R = TypeVar("R")
T = TypeVar("T", bound=Counted)


def acts(method: Callable[Concatenate[T, P], R]) -> Callable[Concatenate[T, P], R]:
    """`method` may change what the machine shows: each call counts in `changes`."""

    @functools.wraps(method)
    def counted(self: T, /, *args: P.args, **kwargs: P.kwargs) -> R:
        self.changes += 1
        return method(self, *args, **kwargs)

    return counted
