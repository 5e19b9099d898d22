from __future__ import annotations

from collections.abc import Iterator

import pytest

from tests.site.stand import Site, site


@pytest.fixture(scope="module")
def abc(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Site]:
    """A router and three daemons: a and c clients of the router, b a peer on its own port."""
    with site(tmp_path_factory.mktemp("site")) as stand:
        stand.start_daemons({"a": "client", "b": "peer", "c": "client"})
        yield stand
