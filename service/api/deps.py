"""Shared route dependencies as ``Annotated`` aliases."""

from __future__ import annotations

import secrets
from typing import Annotated

from fastapi import Depends, Path, Request, Security
from fastapi.security import APIKeyHeader

from service.core.config import MAP_ID_PATTERN
from service.core.errors import ServiceUnavailableError, UnauthorizedError
from service.core.state import ServiceState

__all__ = ["StateDep", "ApiKeyDep", "MapIdPath", "get_state", "require_api_key"]


def get_state(request: Request) -> ServiceState:
    state = getattr(request.app.state, "reradar", None)
    if state is None:
        raise ServiceUnavailableError("the service is still loading the model and maps; retry shortly")
    return state


StateDep = Annotated[ServiceState, Depends(get_state)]

_api_key_header = APIKeyHeader(name="X-API-Key", auto_error=False,
                               description="API key for mutating endpoints (RERADAR_API_KEY).")


def require_api_key(state: StateDep, key: Annotated[str | None, Security(_api_key_header)]) -> None:
    expected = state.settings.api_key.get_secret_value()
    if not key or not secrets.compare_digest(key.encode(), expected.encode()):
        raise UnauthorizedError("missing or wrong API key: send it in the X-API-Key header")


ApiKeyDep = Annotated[None, Depends(require_api_key)]

MapIdPath = Annotated[str, Path(pattern=MAP_ID_PATTERN, description="Map id: [a-z0-9][a-z0-9_-]{0,63}.")]
