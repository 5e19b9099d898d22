"""asyncua's server, with what the gateway changes in it: each session's services where the
specification asks more than asyncua does (the Call service, per-user attributes, timestamps,
limits), and the identity tokens it accepts.

Subclasses of asyncua's own classes, hooked in where asyncua makes them (`Server(iserver=…)`,
`InternalServer.create_session`); each change is pinned by a test through a real server.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from asyncua import Server, ua
from asyncua.common.utils import ServiceError
from asyncua.crypto import security_policies
from asyncua.crypto.permission_rules import User, UserRole
from asyncua.server.internal_server import InternalServer
from asyncua.server.internal_session import InternalSession, SessionState

from rider.gateway.calls import Calls, Invocation, Role
from rider.gateway.security import Caller

_S = ua.StatusCodes
_USER_EXECUTABLE = ua.AttributeIds.UserExecutable


class GatewaySession(InternalSession):  # type: ignore[misc]
    """One client's session: asyncua's, but for the services below."""

    iserver: GatewayInternalServer

    async def call(self, params: list[ua.CallMethodRequest]) -> list[ua.CallMethodResult]:
        return await self.iserver.calls.call(self, params)

    async def read(self, params: ua.ReadParameters) -> list[ua.DataValue]:
        results = await super().read(params)
        return [
            self._as_asked(rv, dv, params.TimestampsToReturn)
            for rv, dv in zip(params.NodesToRead, results, strict=True)
        ]

    def _as_asked(
        self, rv: ua.ReadValueId, dv: ua.DataValue, timestamps: ua.TimestampsToReturn
    ) -> ua.DataValue:
        """A method's `UserExecutable` says whether this session may call it; a value carries
        the timestamps the client asked for (Part 4, 7.40)."""
        if rv.AttributeId == _USER_EXECUTABLE and dv.Value is not None and dv.Value.Value:
            role = self.iserver.calls.role(rv.NodeId)
            caller = self.user
            may = role is Role.SESSION or (
                role is Role.OPERATOR and isinstance(caller, Caller) and caller.operator
            )
            return dataclasses.replace(dv, Value=ua.Variant(may, ua.VariantType.Boolean))
        if rv.AttributeId != ua.AttributeIds.Value:
            return dv
        T = ua.TimestampsToReturn
        source = timestamps in (T.Source, T.Both)
        server = timestamps in (T.Server, T.Both)
        return dataclasses.replace(
            dv,
            SourceTimestamp=dv.SourceTimestamp if source else None,
            SourcePicoseconds=dv.SourcePicoseconds if source else None,
            ServerTimestamp=dv.ServerTimestamp if server else None,
            ServerPicoseconds=dv.ServerPicoseconds if server else None,
        )


class GatewayInternalServer(InternalServer):  # type: ignore[misc]
    """asyncua's internal server, making `GatewaySession`s and holding the Call service."""

    def __init__(self, user_manager: Any) -> None:
        super().__init__(user_manager=user_manager)
        self.calls = Calls(self.isession)
        self.calls.bind(
            ua.NodeId(ua.ObjectIds.Server_GetMonitoredItems), Role.SESSION, self.monitored_items
        )

    async def monitored_items(self, call: Invocation) -> ua.CallMethodResult:
        """`Server.GetMonitoredItems(SubscriptionId)`: the server and client handles of the
        items of one of the calling session's subscriptions (Part 5, 9.1)."""
        if len(call.arguments) != 1:
            wrong = _S.BadArgumentsMissing if not call.arguments else _S.BadTooManyArguments
            return ua.CallMethodResult(StatusCode=ua.StatusCode(wrong))
        wanted = call.arguments[0].Value
        sub = self.subscription_service.subscriptions.get(wanted)
        if not isinstance(wanted, int) or sub is None:
            return ua.CallMethodResult(StatusCode=ua.StatusCode(_S.BadSubscriptionIdInvalid))
        if sub.session_id != call.session.session_id:
            return ua.CallMethodResult(StatusCode=ua.StatusCode(_S.BadUserAccessDenied))
        items = sub.monitored_item_srv._monitored_items  # asyncua 2.x: no public listing
        servers = [ua.Variant(list(items), ua.VariantType.UInt32)]
        clients = [ua.Variant([m.client_handle for m in items.values()], ua.VariantType.UInt32)]
        return ua.CallMethodResult(OutputArguments=servers + clients)

    def decrypt_user_token(self, isession: Any, token: ua.UserNameIdentityToken) -> tuple[str, str]:
        """A password only encrypted with the gateway's certificate, on every endpoint: every
        UserName token policy names an encrypting security policy (`GatewayServer`), and a
        token that ignores it is refused, never read (docs/plant.md, *Security*)."""
        if token.EncryptionAlgorithm not in PASSWORD_ENCRYPTIONS:
            raise ServiceError(_S.BadIdentityTokenInvalid)
        user, password = super().decrypt_user_token(isession, token)
        return str(user), str(password)

    def verify_x509_token(
        self, isession: Any, token: ua.X509IdentityToken, signature: ua.SignatureData
    ) -> bytes:
        """A certificate given as the user's identity: its signature checked (asyncua), then it
        must be one of `--operator-certs`, or the session is refused at activation."""
        der = super().verify_x509_token(isession, token, signature)
        if not self.user_manager.lists(der):
            raise ServiceError(_S.BadIdentityTokenRejected)
        return bytes(der)

    def create_session(
        self, name: str, user: User | None = None, external: bool = False
    ) -> InternalSession:
        user = user if user is not None else User(role=UserRole.Anonymous)
        return GatewaySession(
            self, self.aspace, self.subscription_service, name, user=user, external=external
        )


PASSWORD_ENCRYPTIONS = (
    "http://www.w3.org/2001/04/xmlenc#rsa-oaep",  # Basic256Sha256
    "http://opcfoundation.org/UA/security/rsa-oaep-sha2-256",  # Aes128_Sha256_RsaOaep, Aes256…
)
"""How a client may encrypt a password (not RSA 1.5, not in plain text)."""

POLICIES = (
    ua.SecurityPolicyType.Basic256Sha256_Sign,
    ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt,
    ua.SecurityPolicyType.Aes128Sha256RsaOaep_Sign,
    ua.SecurityPolicyType.Aes128Sha256RsaOaep_SignAndEncrypt,
    ua.SecurityPolicyType.Aes256Sha256RsaPss_Sign,
    ua.SecurityPolicyType.Aes256Sha256RsaPss_SignAndEncrypt,
)
"""The secure endpoints beside `None`, with the gateway's certificate."""
_TOKEN_POLICY = security_policies.SecurityPolicyBasic256Sha256.URI
"""How a password or a user certificate is protected on the `None` endpoint."""


class GatewayServer(Server):  # type: ignore[misc]
    """asyncua's server, whose endpoints never let a password travel in plain text."""

    def _set_endpoints(self, policy: Any, mode: ua.MessageSecurityMode, level: int) -> None:
        super()._set_endpoints(policy, mode, level)
        endpoint = self.iserver.endpoints[-1]
        own = policy.URI if policy is not security_policies.SecurityPolicyNone else _TOKEN_POLICY
        for token in endpoint.UserIdentityTokens:
            if token.TokenType in (ua.UserTokenType.UserName, ua.UserTokenType.Certificate):
                token.SecurityPolicyUri = own


def open_sessions(iserver: InternalServer) -> list[InternalSession]:
    """The client sessions not closed. asyncua keeps them in a registry with no public listing
    (`InternalServer._external_sessions`, asyncua 2.x; tests/gateway/test_sessions.py pins it)."""
    sessions = getattr(iserver, "_external_sessions", {})
    return [s for s in list(sessions.values()) if s.state is not SessionState.Closed]


__all__ = ["GatewayInternalServer", "GatewayServer", "GatewaySession", "open_sessions"]
