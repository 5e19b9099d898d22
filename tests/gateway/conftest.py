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
def client_certs(tmp_path_factory: pytest.TempPathFactory) -> tuple[Credentials, Credentials]:
    """Two client application certificates: the first listed as an operator's, the other not."""
    tmp = tmp_path_factory.mktemp("clients")
    return make_credentials(tmp / "listed"), make_credentials(tmp / "unlisted")


@pytest.fixture(scope="package")
def gateway(
    plant: Site, creds: Credentials, client_certs: tuple[Credentials, Credentials]
) -> Iterator[GatewayProc]:
    """`rider gateway` on the plant's router, with operators (by password, and by the listed
    certificate), a certificate of its own and short timeouts."""
    operators = client_certs[0].certificate.parent / "operators"
    operators.mkdir()
    (operators / "listed.der").write_bytes(client_certs[0].certificate.read_bytes())
    more = ("--operator-certs", str(operators))
    with running_gateway(plant.rider_cmd(), creds, *more) as gw:
        yield gw
