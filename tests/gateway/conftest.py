from __future__ import annotations

from collections.abc import Iterator

import pytest

from tests.gateway.support import Credentials, GatewayProc, make_credentials, running_gateway
from tests.site.stand import Site, site


@pytest.fixture(scope="package")
def creds(tmp_path_factory: pytest.TempPathFactory) -> Credentials:
    return make_credentials(tmp_path_factory.mktemp("secrets"))


@pytest.fixture(scope="package")
def plant(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Site]:
    """A router and one machine, m1, that joined it (the fast simulator)."""
    with site(tmp_path_factory.mktemp("plant")) as stand:
        stand.start_daemons({"m1": "client"})
        yield stand


@pytest.fixture(scope="package")
def gateway(plant: Site, creds: Credentials) -> Iterator[GatewayProc]:
    """`rider gateway` on the plant's router, with operators, a certificate and short timeouts."""
    with running_gateway(plant.rider_cmd(), creds) as gw:
        yield gw
