"""Monitored items outlive a forgotten machine (issue 56, point 2).

A machine gone longer than `--forget-after` leaves the address space. asyncua would then drop
the monitored items on its nodes silently (its delete hook calls them without awaiting, and
forgets their handles), so a client kept waiting on an item that could never deliver again.
Here, before the nodes go, each item on them is told `BadNodeIdUnknown` (OPC UA Part 4: the
node is gone) and kept aside by node id; when the machine comes back under the same node ids
its items are put back on the new nodes and deliver again, without the client doing anything.
An item deleted meanwhile (its client went) is dropped from the side too.

This reaches into asyncua's address space (`_nodes`, `_handle_to_attribute_map`): asyncua
2.x, pinned by requirements/ and by tests/gateway/test_parts.py.
"""

from __future__ import annotations

import logging
from collections.abc import Awaitable, Callable, Iterable
from datetime import UTC, datetime
from typing import Any

from asyncua import ua
from asyncua.server.address_space import AddressSpace

log = logging.getLogger(__name__)

Callback = Callable[..., Awaitable[None]]
_VALUE = ua.AttributeIds.Value


class Parking:
    """The monitored items of forgotten nodes, by node id, until the nodes come back."""

    def __init__(self, aspace: AddressSpace) -> None:
        self._aspace = aspace
        self._parked: dict[ua.NodeId, dict[int, Callback]] = {}
        delete = aspace.delete_datachange_callback

        def delete_callback(handle: int) -> None:
            """asyncua's, but for an item parked on a node that is gone."""
            where = aspace._handle_to_attribute_map.get(handle)
            if where is not None and where[0] in self._parked:
                aspace._handle_to_attribute_map.pop(handle)
                self._parked[where[0]].pop(handle, None)
                return
            delete(handle)

        aspace.delete_datachange_callback = delete_callback

    @property
    def items(self) -> int:
        """Monitored items waiting for their nodes."""
        return sum(len(callbacks) for callbacks in self._parked.values())

    async def park(self, nodeids: Iterable[ua.NodeId]) -> int:
        """Before `nodeids` are deleted: tell their monitored items `BadNodeIdUnknown` and keep
        them aside. Returns how many were parked."""
        now = datetime.now(UTC)
        gone = ua.DataValue(
            StatusCode=ua.StatusCode(ua.StatusCodes.BadNodeIdUnknown), ServerTimestamp=now
        )
        count = 0
        for nid in nodeids:
            value = self._value(nid)
            if value is None or not value.datachange_callbacks:
                continue
            callbacks = dict(value.datachange_callbacks)
            value.datachange_callbacks.clear()
            self._parked.setdefault(nid, {}).update(callbacks)
            for handle, callback in callbacks.items():
                try:
                    await callback(handle, gone)
                except Exception:  # one client's item must not keep the others waiting
                    log.exception("event=park_notify_failed node=%s", nid.to_string())
            count += len(callbacks)
        return count

    def unpark(self, nodeids: Iterable[ua.NodeId]) -> int:
        """`nodeids` exist again: their parked monitored items are theirs again (the next write
        delivers). Returns how many came back."""
        count = 0
        for nid in nodeids:
            callbacks = self._parked.get(nid)
            value = self._value(nid)
            if not callbacks or value is None:
                continue
            del self._parked[nid]
            value.datachange_callbacks.update(callbacks)
            count += len(callbacks)
        return count

    def _value(self, nid: ua.NodeId) -> Any:
        node = self._aspace._nodes.get(nid)
        return None if node is None else node.attributes.get(_VALUE)
