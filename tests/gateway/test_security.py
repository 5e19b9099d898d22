"""Security as documented (issue 56, point 4 and the security modes): a password sent in plain
text is refused on every endpoint, a user certificate that is not an operator's is refused at
session activation, and Sign and SignAndEncrypt endpoints serve with Basic256Sha256,
Aes128_Sha256_RsaOaep and Aes256_Sha256_RsaPss. A real gateway, asyncua's client."""

from __future__ import annotations

import dataclasses

import pytest
from asyncua import Client, ua
from asyncua.crypto.security_policies import SecurityPolicyNone

from tests.gateway.support import Credentials, GatewayProc
from tests.gateway.ua import call, connected, run

pytestmark = pytest.mark.integration
OPERATOR = "operator"
POLICIES = ("Basic256Sha256", "Aes128Sha256RsaOaep", "Aes256Sha256RsaPss")
MODES = ("Sign", "SignAndEncrypt")


class PlainText(Client):  # type: ignore[misc]
    """A client that sends its password as is, whatever the server's token policy says."""

    def server_policy(self, token_type: ua.UserTokenType) -> ua.UserTokenPolicy:
        policy = super().server_policy(token_type)
        return dataclasses.replace(policy, SecurityPolicyUri=SecurityPolicyNone.URI)


def _security(policy: str, mode: str, client: Credentials, server: Credentials) -> str:
    parts = [client.certificate, client.private_key, server.certificate]
    return ",".join([policy, mode, *map(str, parts)])


@pytest.mark.hazard("H52")
def test_a_password_in_plain_text_is_refused_on_every_endpoint(
    gateway: GatewayProc, creds: Credentials, client_certs: tuple[Credentials, Credentials]
) -> None:
    async def attempt(security: str | None) -> None:
        client = PlainText(gateway.url, timeout=10)
        client.set_user(OPERATOR)
        client.set_password(creds.password)
        if security is not None:
            await client.set_security_string(security)
        with pytest.raises(ua.uaerrors.BadIdentityTokenInvalid):
            async with client:
                pass

    async def body() -> None:
        await attempt(None)
        await attempt(_security("Basic256Sha256", "SignAndEncrypt", client_certs[1], creds))
        # The same password, encrypted as the token policy says, is an operator's.
        async with connected(gateway.url, OPERATOR, creds.password) as c:
            assert (await call(c, "m1", "Stop")).code == "RESP_DONE"

    run(body())


@pytest.mark.hazard("H52")
def test_a_user_certificate_that_is_no_operators_is_refused_at_activation(
    gateway: GatewayProc, client_certs: tuple[Credentials, Credentials]
) -> None:
    async def user_cert(who: Credentials) -> Client:
        client = Client(gateway.url, timeout=10)
        await client.load_client_certificate(str(who.certificate))
        await client.load_private_key(who.private_key)
        return client

    listed, unlisted = client_certs

    async def body() -> None:
        with pytest.raises(ua.uaerrors.BadIdentityTokenRejected):
            async with await user_cert(unlisted):
                pass
        async with await user_cert(listed) as c:
            assert (await call(c, "m1", "Stop")).code == "RESP_DONE"

    run(body())


def test_sign_and_sign_and_encrypt_serve_with_three_policies(
    gateway: GatewayProc, creds: Credentials, client_certs: tuple[Credentials, Credentials]
) -> None:
    async def body() -> None:
        async with connected(gateway.url) as c:
            offered = {
                (e.SecurityPolicyUri.rpartition("#")[2], e.SecurityMode.name)
                for e in await c.get_endpoints()
            }
        uris = ("Basic256Sha256", "Aes128_Sha256_RsaOaep", "Aes256_Sha256_RsaPss")
        assert offered == {("None", "None_")} | {(u, m) for u in uris for m in MODES}
        for policy in POLICIES:
            for mode in MODES:
                security = _security(policy, mode, client_certs[1], creds)
                async with connected(gateway.url, OPERATOR, creds.password, security=security) as c:
                    got = await call(c, "m1", "Stop")
                    assert got.code == "RESP_DONE", (policy, mode, got)

    run(body())
