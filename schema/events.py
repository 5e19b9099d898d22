"""The machine's event history: one `Event` per thing that happened, read on `machine/<id>/events`.

Each event has a kind (`EventKind`) and typed details, one model per kind, told apart by their
`kind` field. A reader that meets a kind newer than itself keeps the details as a plain mapping
instead of failing, so old Riders can read a newer machine's history.

One import for all of it; the parts: the kinds (schema/event_kinds.py), the wire models
(schema/event_models.py) and which events to read (schema/event_query.py). How events read for
people is not wire: common/event_words.py (one line per event) and common/event_summary.py (the
history counted).
"""

from __future__ import annotations

from .event_kinds import *  # noqa: F403 - this module is the one import for all of them
from .event_models import *  # noqa: F403
from .event_query import *  # noqa: F403
