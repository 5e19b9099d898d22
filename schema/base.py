"""Base classes shared by all wire models."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict


class WireModel(BaseModel):
    """A request on the wire: unknown fields and wrong types are refused, never coerced.

    Enum fields opt out of strictness with `Field(strict=False)` so they accept their string value.
    """

    model_config = ConfigDict(extra="forbid", frozen=True, strict=True)


class OpenWireModel(BaseModel):
    """A record read by old clients: new fields from newer senders are ignored, not refused."""

    model_config = ConfigDict(extra="ignore", frozen=True)
