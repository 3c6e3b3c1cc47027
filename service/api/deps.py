"""Shared route dependencies as ``Annotated`` aliases."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import Depends, Path, Request, Security
from fastapi.security import APIKeyHeader

from service.api.scan_input import (
    refuse_repeated_fields,
    refuse_text_fields_sent_as_files,
    refuse_unknown_fields,
)
from service.core.config import MAP_ID_PATTERN
from service.core.errors import ServiceUnavailableError, UnauthorizedError, UnsupportedMediaError
from service.core.state import ServiceState

__all__ = ["StateDep", "ApiKeyDep", "OperatorDep", "VehicleDep", "FormDep", "MapIdPath", "get_state",
           "require_operator", "require_vehicle", "require_form", "form_fields"]


def get_state(request: Request) -> ServiceState:
    state = getattr(request.app.state, "reradar", None)
    if state is None:
        raise ServiceUnavailableError("the service is still loading the model and maps; retry shortly")
    return state


StateDep = Annotated[ServiceState, Depends(get_state)]

_api_key_header = APIKeyHeader(name="X-API-Key", auto_error=False,
                               description="Operator key (RERADAR_API_KEY) for registering and deleting maps.")


def require_operator(request: Request, key: Annotated[str | None, Security(_api_key_header)]) -> None:
    """The request guard (``service.api.middleware``) authenticates before the body is read and records the
    caller; this re-checks the record, so a route can never be reached unauthenticated if the guard is
    bypassed (e.g. mounted elsewhere)."""
    if request.scope.get("state", {}).get("principal") != "operator":
        raise UnauthorizedError("missing or wrong operator key: send it in the X-API-Key header")


OperatorDep = Annotated[None, Depends(require_operator)]
ApiKeyDep = OperatorDep  # the name the routes used before vehicle keys existed


def require_vehicle(request: Request) -> None:
    """As ``require_operator``, for vehicle-class routes (``service.api.security``): the guard admitted the
    caller with a vehicle or operator key, or as a loopback client while no vehicle key is configured."""
    if request.scope.get("state", {}).get("principal") not in ("operator", "vehicle", "loopback"):
        raise UnauthorizedError("this endpoint needs a vehicle or operator key in the X-API-Key header")


VehicleDep = Annotated[None, Depends(require_vehicle)]


def require_form(request: Request) -> None:
    """Refuse a body that is not a form (415) before its fields are validated, so a JSON body is told the
    encoding to use instead of "field required" for every form field. Files need multipart/form-data; an
    url-encoded form passes here and is told which file is missing."""
    ctype = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if ctype not in ("multipart/form-data", "application/x-www-form-urlencoded"):
        raise UnsupportedMediaError(f"unsupported Content-Type {ctype or '(none)'!r}: {request.method} "
                                    f"{request.url.path} takes multipart/form-data (form fields and files)")


FormDep = Annotated[None, Depends(require_form)]


def form_fields(*allowed: str, files: tuple[str, ...] = ()) -> Any:
    """A dependency (``Depends``) refusing a form whose fields repeat, fall outside ``allowed`` or, being text
    (not in ``files``), arrive as file parts (400 naming them), as inline scans on ``/localize`` and
    ``/retrieve`` are: FastAPI's form parameters take a repeated field's last value (two ``map_id``: the second
    map registered), drop unknown fields without a word and read a text field sent as a file as missing. The
    body was parsed before dependencies run; ``request.form()`` returns that parse."""

    async def check_form_fields(request: Request) -> None:
        form = await request.form()
        refuse_repeated_fields(form)
        refuse_unknown_fields(form, allowed)
        refuse_text_fields_sent_as_files(form, files)

    return Depends(check_form_fields)


MapIdPath = Annotated[str, Path(pattern=MAP_ID_PATTERN, description="Map id: [a-z0-9][a-z0-9_-]{0,63}.")]
