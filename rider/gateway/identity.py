"""What the gateway says it is and what it takes: the product's identity (BuildInfo, not
asyncua's "FreeOpcUa Python Server 1.0pre"), its limits in ServerCapabilities (enforced by
rider/gateway/uaserver.py, not only written), and the server's diagnostics summary."""

from __future__ import annotations

from dataclasses import dataclass
from datetime import UTC, datetime
from importlib import metadata

from asyncua import Server, ua

from .calls import MAX_ARGUMENT_BYTES, MAX_ARGUMENTS

PRODUCT_URI = "urn:ride-machine:product:gateway"
MANUFACTURER = "ride-machine"
PRODUCT_NAME = "ride-machine gateway"
DISTRIBUTION = "ride-machine"
_I = ua.ObjectIds


@dataclass(frozen=True)
class Limits:
    """What one gateway serves at most; each is in ServerCapabilities and enforced."""

    sessions: int = 50
    subscriptions: int = 500
    subscriptions_per_session: int = 20
    monitored_items: int = 50_000
    monitored_items_per_subscription: int = 5_000
    nodes_per_operation: int = 1_000
    """Read, Browse, TranslateBrowsePaths, CreateMonitoredItems: per request."""
    methods_per_call: int = 100


def version() -> tuple[str, datetime]:
    """The installed product's version, and when it was built (its metadata's time)."""
    try:
        dist = metadata.distribution(DISTRIBUTION)
    except metadata.PackageNotFoundError:
        return "unknown", datetime.fromtimestamp(0, UTC)
    meta = [f for f in dist.files or [] if f.name == "METADATA"]
    try:
        built = datetime.fromtimestamp(meta[0].locate().stat().st_mtime, UTC)  # type: ignore[attr-defined]
    except (OSError, IndexError):
        built = datetime.fromtimestamp(0, UTC)
    return str(dist.version), built


async def describe(server: Server, limits: Limits) -> None:
    """BuildInfo and ServerCapabilities, written once at start."""
    number, built = version()
    await server.set_build_info(PRODUCT_URI, MANUFACTURER, PRODUCT_NAME, number, number, built)
    caps = {
        _I.Server_ServerCapabilities_MaxSessions: (limits.sessions, ua.VariantType.UInt32),
        _I.Server_ServerCapabilities_MaxSubscriptions: (
            limits.subscriptions,
            ua.VariantType.UInt32,
        ),
        _I.Server_ServerCapabilities_MaxSubscriptionsPerSession: (
            limits.subscriptions_per_session,
            ua.VariantType.UInt32,
        ),
        _I.Server_ServerCapabilities_MaxMonitoredItems: (
            limits.monitored_items,
            ua.VariantType.UInt32,
        ),
        _I.Server_ServerCapabilities_MaxMonitoredItemsPerSubscription: (
            limits.monitored_items_per_subscription,
            ua.VariantType.UInt32,
        ),
        _I.Server_ServerCapabilities_MaxStringLength: (MAX_ARGUMENT_BYTES, ua.VariantType.UInt32),
        _I.Server_ServerCapabilities_MaxByteStringLength: (
            MAX_ARGUMENT_BYTES,
            ua.VariantType.UInt32,
        ),
        _I.Server_ServerCapabilities_MaxArrayLength: (MAX_ARGUMENTS, ua.VariantType.UInt32),
        _I.Server_ServerCapabilities_MinSupportedSampleRate: (0.0, ua.VariantType.Double),
        _I.Server_ServerCapabilities_LocaleIdArray: (["en"], ua.VariantType.String),
    }
    per_op = limits.nodes_per_operation
    for name in ("Read", "Browse", "TranslateBrowsePathsToNodeIds", "RegisterNodes"):
        caps[getattr(_I, f"Server_ServerCapabilities_OperationLimits_MaxNodesPer{name}")] = (
            per_op,
            ua.VariantType.UInt32,
        )
    caps[_I.Server_ServerCapabilities_OperationLimits_MaxMonitoredItemsPerCall] = (
        per_op,
        ua.VariantType.UInt32,
    )
    caps[_I.Server_ServerCapabilities_OperationLimits_MaxNodesPerMethodCall] = (
        limits.methods_per_call,
        ua.VariantType.UInt32,
    )
    # Nobody may write, edit the space or its history: those limits are 0 (no such service).
    for name in ("Write", "NodeManagement", "HistoryUpdateData", "HistoryUpdateEvents"):
        caps[getattr(_I, f"Server_ServerCapabilities_OperationLimits_MaxNodesPer{name}")] = (
            0,
            ua.VariantType.UInt32,
        )
    for nid, (value, vtype) in caps.items():
        await server.write_attribute_value(ua.NodeId(nid), ua.DataValue(ua.Variant(value, vtype)))


@dataclass
class Counts:
    """Sessions and subscriptions since start, for the diagnostics summary."""

    sessions: int = 0
    rejected_sessions: int = 0
    security_rejected: int = 0
    timed_out: int = 0
    subscriptions: int = 0
    rejected_requests: int = 0


async def diagnose(server: Server, counts: Counts, sessions: int, subscriptions: int) -> None:
    """The ServerDiagnosticsSummary as it is now (the gateway refreshes it every second)."""
    values = {
        "CurrentSessionCount": sessions,
        "CumulatedSessionCount": counts.sessions,
        "SecurityRejectedSessionCount": counts.security_rejected,
        "RejectedSessionCount": counts.rejected_sessions,
        "SessionTimeoutCount": counts.timed_out,
        "CurrentSubscriptionCount": subscriptions,
        "CumulatedSubscriptionCount": counts.subscriptions,
        "RejectedRequestsCount": counts.rejected_requests,
    }
    summary = ua.ServerDiagnosticsSummaryDataType(**values)
    base = _I.Server_ServerDiagnostics_ServerDiagnosticsSummary
    await server.write_attribute_value(
        ua.NodeId(base), ua.DataValue(ua.Variant(summary, ua.VariantType.ExtensionObject))
    )
    for name, value in values.items():
        nid = ua.NodeId(getattr(_I, f"Server_ServerDiagnostics_ServerDiagnosticsSummary_{name}"))
        await server.write_attribute_value(
            nid, ua.DataValue(ua.Variant(value, ua.VariantType.UInt32))
        )


async def enable_diagnostics(server: Server) -> None:
    flag = ua.NodeId(_I.Server_ServerDiagnostics_EnabledFlag)
    await server.write_attribute_value(flag, ua.DataValue(ua.Variant(True, ua.VariantType.Boolean)))
