"""The bus tests' Zenoh session: a peer of its own, on no network (its queries reach its own
queryables)."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
import zenoh


@pytest.fixture(scope="module")
def session() -> Iterator[zenoh.Session]:
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("listen/endpoints", "[]")
    conf.insert_json5("scouting/multicast/enabled", "false")
    s = zenoh.open(conf)
    yield s
    s.close()
