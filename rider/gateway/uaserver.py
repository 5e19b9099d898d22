"""asyncua's server, with what the gateway changes in it: each session's services where the
specification asks more than asyncua does (the Call service, per-user attributes, timestamps,
limits), and the identity tokens it accepts.

Subclasses of asyncua's own classes, hooked in where asyncua makes them (`Server(iserver=…)`,
`InternalServer.create_session`); each change is pinned by a test through a real server.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

from asyncua import Server, ua
from asyncua.common.utils import ServiceError
from asyncua.crypto import security_policies
from asyncua.crypto.permission_rules import User, UserRole
from asyncua.server.internal_server import InternalServer
from asyncua.server.internal_session import InternalSession, SessionState
from asyncua.ua.uaprotocol_auto import DataChangeFilter

from ride_machine.rider.gateway import nodeset_cache

from .calls import Calls, Invocation, Role
from .identity import Counts, Limits
from .security import Caller

_S = ua.StatusCodes
_FILTER_NOT_ALLOWED: int = _S.BadFilterNotAllowed
_DEADBAND_INVALID: int = _S.BadDeadbandFilterInvalid
_USER_EXECUTABLE = ua.AttributeIds.UserExecutable


class GatewaySession(InternalSession):  # type: ignore[misc]
    """One client's session: asyncua's, but for the services below."""

    iserver: GatewayInternalServer

    async def create_session(
        self, params: ua.CreateSessionParameters, sockname: tuple[str, int] | None = None
    ) -> ua.CreateSessionResult:
        """At most `Limits.sessions` sessions (ServerCapabilities.MaxSessions)."""
        if len(open_sessions(self.iserver)) > self.iserver.limits.sessions:  # this one counts
            self.iserver.counts.rejected_sessions += 1
            await self.close_session()
            raise ServiceError(_S.BadTooManySessions)
        self.iserver.counts.sessions += 1
        return await super().create_session(params, sockname)

    def activate_session(
        self, params: ua.ActivateSessionParameters, peer_certificate: bytes | None
    ) -> ua.ActivateSessionResult:
        try:
            return super().activate_session(params, peer_certificate)
        except (ServiceError, ua.UaStatusCodeError):
            self.iserver.counts.security_rejected += 1
            raise

    async def call(self, params: list[ua.CallMethodRequest]) -> list[ua.CallMethodResult]:
        self._bounded(len(params), self.iserver.limits.methods_per_call)
        return await self.iserver.calls.call(self, params)

    async def browse(self, params: ua.BrowseParameters) -> list[ua.BrowseResult]:
        self._bounded(len(params.NodesToBrowse), self.iserver.limits.nodes_per_operation)
        results: list[ua.BrowseResult] = await super().browse(params)
        return results

    async def translate_browsepaths_to_nodeids(
        self, params: list[ua.BrowsePath]
    ) -> list[ua.BrowsePathResult]:
        self._bounded(len(params), self.iserver.limits.nodes_per_operation)
        results: list[ua.BrowsePathResult] = await super().translate_browsepaths_to_nodeids(params)
        return results

    async def create_subscription(
        self, params: ua.CreateSubscriptionParameters, callback: Any, request_callback: Any = None
    ) -> ua.CreateSubscriptionResult:
        """At most `Limits.subscriptions_per_session` of them (and asyncua's own server-wide
        bound, set to `Limits.subscriptions`)."""
        if len(self._subscriptions()) >= self.iserver.limits.subscriptions_per_session:
            raise ServiceError(_S.BadTooManySubscriptions)
        self.iserver.counts.subscriptions += 1
        return await super().create_subscription(params, callback, request_callback)

    async def create_monitored_items(
        self, params: ua.CreateMonitoredItemsParameters
    ) -> list[ua.MonitoredItemCreateResult]:
        """Items past the limits are refused `BadTooManyMonitoredItems`, and a deadband the
        item cannot take `BadDeadbandFilterInvalid` / `BadFilterNotAllowed` (Part 4, 7.22.2):
        a PercentDeadband needs an `EURange` (it is taken as that share of the range)."""
        limits = self.iserver.limits
        self._bounded(len(params.ItemsToCreate), limits.nodes_per_operation)
        sub = self.subscription_service.subscriptions.get(params.SubscriptionId)
        if sub is None or sub.session_id != self.session_id:
            raise ServiceError(_S.BadSubscriptionIdInvalid)
        room = min(
            limits.monitored_items_per_subscription - len(sub.monitored_item_srv._monitored_items),
            limits.monitored_items - self.iserver.monitored_items(),
        )
        refusals: dict[int, int] = {}
        for i, item in enumerate(params.ItemsToCreate):
            status = filter_refusal(self.iserver, item)
            if status is None and room <= 0:
                status = _S.BadTooManyMonitoredItems
            if status is not None:
                refusals[i] = status
            else:
                room -= 1
        accepted = [it for i, it in enumerate(params.ItemsToCreate) if i not in refusals]
        done = iter(
            await super().create_monitored_items(
                dataclasses.replace(params, ItemsToCreate=accepted)
            )
            if accepted
            else []
        )
        return [
            ua.MonitoredItemCreateResult(StatusCode=ua.StatusCode(refusals[i]))
            if i in refusals
            else next(done)
            for i in range(len(params.ItemsToCreate))
        ]

    def _subscriptions(self) -> list[Any]:
        subs = self.subscription_service.subscriptions.values()
        return [s for s in subs if s.session_id == self.session_id]

    def _bounded(self, count: int, limit: int) -> None:
        if count > limit:
            self.iserver.counts.rejected_requests += 1
            raise ServiceError(_S.BadTooManyOperations)

    async def read(self, params: ua.ReadParameters) -> list[ua.DataValue]:
        self._bounded(len(params.NodesToRead), self.iserver.limits.nodes_per_operation)
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

    def __init__(self, user_manager: Any, limits: Limits | None = None) -> None:
        super().__init__(user_manager=user_manager)
        self.nodeset: Path | None = None
        """The standard address space's shelf (rider/gateway/nodeset_cache.py); None: build
        it in memory."""
        self.limits = limits or Limits()
        self.counts = Counts()
        self.max_subscriptions = self.limits.subscriptions  # asyncua's own, server-wide
        self.calls = Calls(self.isession)
        self.calls.bind(
            ua.NodeId(ua.ObjectIds.Server_GetMonitoredItems), Role.SESSION, self.get_monitored_items
        )

    async def load_standard_address_space(self, shelf_file: Path | None = None) -> None:
        """From `nodeset` when there is one: its nodes read as they are touched."""
        if self.nodeset is not None:
            nodeset_cache.load(self, self.nodeset)
        else:
            await super().load_standard_address_space(None)

    def monitored_items(self) -> int:
        """Monitored items of every subscription now."""
        subs = self.subscription_service.subscriptions.values()
        return sum(len(s.monitored_item_srv._monitored_items) for s in subs)

    async def get_monitored_items(self, call: Invocation) -> ua.CallMethodResult:
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


_NUMBERS = {
    ua.VariantType.SByte, ua.VariantType.Byte, ua.VariantType.Int16, ua.VariantType.UInt16,
    ua.VariantType.Int32, ua.VariantType.UInt32, ua.VariantType.Int64, ua.VariantType.UInt64,
    ua.VariantType.Float, ua.VariantType.Double,
}  # fmt: skip


def filter_refusal(iserver: InternalServer, item: ua.MonitoredItemCreateRequest) -> int | None:
    """Why a data change filter cannot be taken on the item (None: it can; a PercentDeadband
    is turned into the absolute deadband it means on the item's EURange)."""
    flt = item.RequestedParameters.Filter
    # The wire decodes uaprotocol_auto's DataChangeFilter; `ua.DataChangeFilter` is a subclass.
    if not isinstance(flt, DataChangeFilter) or flt.DeadbandType == ua.DeadbandType.None_:
        return None
    nid = item.ItemToMonitor.NodeId
    if item.ItemToMonitor.AttributeId != ua.AttributeIds.Value:
        return _FILTER_NOT_ALLOWED
    if not _numeric(iserver, nid):
        return _FILTER_NOT_ALLOWED
    if flt.DeadbandType != ua.DeadbandType.Percent:
        return None
    eurange = iserver.aspace.read_attribute_value(
        ua.NodeId(f"{nid.Identifier}/EURange", nid.NamespaceIndex), ua.AttributeIds.Value
    )
    span = eurange.Value.Value if eurange.Value is not None else None
    if not isinstance(span, ua.Range) or not 0 <= flt.DeadbandValue <= 100:
        return _DEADBAND_INVALID
    flt.DeadbandType = ua.DeadbandType.Absolute
    flt.DeadbandValue = flt.DeadbandValue / 100 * (span.High - span.Low)
    return None


def _numeric(iserver: InternalServer, nid: ua.NodeId) -> bool:
    """Whether the variable's DataType is a number (a deadband means something on it)."""
    dtype = iserver.aspace.read_attribute_value(nid, ua.AttributeIds.DataType)
    node = dtype.Value.Value if dtype.Value is not None else None
    numbers = {v.value for v in _NUMBERS}
    return isinstance(node, ua.NodeId) and node.NamespaceIndex == 0 and node.Identifier in numbers


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
