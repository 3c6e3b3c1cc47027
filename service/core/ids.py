"""Identifier patterns shared by the API schemas and the settings; importing this module loads nothing
else, so the vehicle client (``service.client`` -> ``service.api.schemas``) stays free of the server's
dependencies."""

from __future__ import annotations

__all__ = ["MAP_ID_PATTERN", "SESSION_ID_PATTERN"]

#: Map ids: lower-case letters, digits, ``_`` and ``-``; no dots or slashes, so an id can never escape
#: the maps directory.
MAP_ID_PATTERN = r"^[a-z0-9][a-z0-9_-]{0,63}$"

#: Tracking session ids chosen by clients (e.g. a vehicle id plus a drive counter).
SESSION_ID_PATTERN = r"^[A-Za-z0-9_.:-]{1,64}$"
