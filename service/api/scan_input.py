"""Parse a request that carries a scan either inline (multipart/form-data) or by reference (JSON)."""

from __future__ import annotations

import json
import math
import re
from collections import Counter
from collections.abc import AsyncGenerator, Callable, Iterable
from contextlib import aclosing
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from fastapi import Request, params
from fastapi.exceptions import RequestValidationError
from fastapi.routing import APIRoute
from pydantic import BaseModel, ValidationError
from pydantic_core import from_json
from python_multipart.multipart import parse_options_header
from starlette.concurrency import run_in_threadpool
from starlette.datastructures import FormData, UploadFile
from starlette.formparsers import MultiPartParser

from reradar_core.errors import ScanTooLargeError
from reradar_core.features import ScanFeatures
from reradar_core.io.presets import PRESETS
from reradar_core.io.scan import (
    LOSSY_FORMATS,
    NpyLayout,
    check_header_size,
    scan_header,
    sniff_scan_format,
    why_format_refused,
)
from service.api.security import caller_of
from service.core.errors import (
    BadRequestError,
    NotFoundError,
    PayloadTooLargeError,
    UnsupportedMediaError,
    shorten_echo,
)
from service.core.state import ServiceState

__all__ = ["ScanInput", "read_scan_input", "scan_request_body", "UnsupportedMediaError", "check_scan_upload",
           "read_scan_upload", "parse_scan_layout", "SCAN_LAYOUTS", "SCAN_LAYOUT_DESCRIPTION", "read_multipart_form",
           "refuse_repeated_fields", "refuse_unknown_fields", "refuse_text_fields_sent_as_files",
           "refuse_files_sent_as_text", "validate_json_body", "refuse_duplicate_json_keys", "ClosedFormRoute"]

# ASCII digits only, the whole text (``fullmatch``: ``$`` would let a trailing newline through, ``\d`` other scripts'
# digits, which ``float`` reads)
_TOP_K_FORM = re.compile(r"[0-9]{1,6}")
_FLOAT_FORM = re.compile(r"[+-]?([0-9]+(\.[0-9]*)?|\.[0-9]+)([eE][+-]?[0-9]{1,3})?")


#: Bytes of an upload read to find its header (a PNG's IHDR is in the first 33, an .npy header under 10 kB).
HEADER_BYTES = 65536


SCAN_LAYOUT_DESCRIPTION = (
    "What an .npy `scan` holds: `polar` (default) = an (A, R) power array, uint8 or float in [0, 1], uniform "
    "azimuths, geometry from `preset`; `navtech` = the Navtech PNG's pixels as a uint8 (A, 11 + R) array "
    "(11 metadata columns, then the range bins), decoded exactly as the PNG (same azimuths, timestamps and "
    "answer) without PNG decompression: 2.7x the bytes of the PNG, ~5-10 ms less server time per scan. "
    "Ignored for PNG uploads.")
SCAN_LAYOUT_SCHEMA: dict[str, Any] = {"type": "string", "enum": ["polar", "navtech"], "default": "polar",
                                      "description": SCAN_LAYOUT_DESCRIPTION}

#: Values of the ``scan_layout`` form field (what an .npy upload holds; ``reradar_core.io.scan.NpyLayout``).
SCAN_LAYOUTS: tuple[NpyLayout, ...] = ("polar", "navtech")


def parse_scan_layout(value: object) -> NpyLayout:
    """The ``scan_layout`` form field (default ``polar``). Raises BadRequestError (400) for another value."""
    if value is None or value == "":
        return "polar"
    if value == "polar" or value == "navtech":
        return value
    shown = shorten_echo(value) if isinstance(value, str) else value  # client text: cut, as preset values are
    raise BadRequestError(f"unknown scan_layout {shown!r}; choose one of {list(SCAN_LAYOUTS)}")


async def read_scan_upload(upload: UploadFile, max_pixels: int,
                           scan_layout: NpyLayout = "polar") -> tuple[bytes, str]:
    """The bytes of an uploaded scan and the file name to decode them under, after checking its header: only
    the first ``HEADER_BYTES`` are read before the checks, so a refused file is never held in memory whole."""
    head = await upload.read(HEADER_BYTES)
    size = upload.size if upload.size is not None else len(head)
    filename = check_scan_upload(head, max_pixels, size, scan_layout)
    await upload.seek(0)
    data = await upload.read()
    await upload.close()
    return data, filename


def check_scan_upload(data: bytes, max_pixels: int, size: int | None = None,
                      scan_layout: NpyLayout = "polar") -> str:
    """Size an uploaded scan from its header, before anything is decoded; returns the file name to decode it
    under (``scan.png`` / ``scan.npy``: the content decides, not the client's file name). ``data`` may be the
    file's beginning only, ``size`` its whole length.

    Raises:
        UnsupportedMediaError (415): a lossy image (JPEG, WebP, ...). ScanFormatError (422): not a Navtech PNG
        or .npy, bad header, too few azimuths / bins. PayloadTooLargeError (413): more than ``max_pixels`` or a
        side above ``MAX_SCAN_SIDE``.
    """
    kind = sniff_scan_format(data)
    if kind in LOSSY_FORMATS:
        raise UnsupportedMediaError(f"{kind.upper()} images are {why_format_refused(kind)} and are not accepted "
                                    "as radar scans: send the radar's lossless Navtech PNG or an (A, R) .npy array")
    header = scan_header(data, size)
    try:
        check_header_size(header, max_pixels, scan_layout)
    except ScanTooLargeError as exc:
        raise PayloadTooLargeError(str(exc).replace("accepted are", "the service accepts")) from None
    return f"scan.{header.format}"


def refuse_repeated_fields(form: FormData) -> None:
    """400 when a form field (or file) is given more than once: last-one-wins would silently pick a map, a
    prior or a scan the client may not have meant."""
    repeated = sorted(k for k, n in Counter(k for k, _ in form.multi_items()).items() if n > 1)
    if repeated:
        raise BadRequestError(f"form fields {repeated} are given more than once; send each field once")


def refuse_unknown_fields(form: FormData, allowed: Iterable[str]) -> None:
    """400 naming the form fields (or files) outside ``allowed``: a misspelt optional field would otherwise be
    dropped without a word (``prest=mulran`` localizing with the default preset)."""
    names = list(allowed)
    unknown = sorted(set(form.keys()) - set(names))
    if unknown:
        shown = ", ".join(repr(shorten_echo(k)) for k in unknown[:5]) + (f" (+{len(unknown) - 5} more)"
                                                                        if len(unknown) > 5 else "")
        raise BadRequestError(f"unexpected form fields [{shown}]; allowed: {', '.join(names)}")


def refuse_text_fields_sent_as_files(form: FormData, files: Iterable[str]) -> None:
    """400 naming the text fields that arrived as file parts (``-F session_id=@sid.txt``; some HTTP libraries
    send every field so): read as text they would be missing, and the request would run without them - a
    tracking session silently dropped, a preset ignored. ``files`` are the form's file fields."""
    file_fields = set(files)
    as_files = sorted({k for k, v in form.multi_items() if k not in file_fields and not isinstance(v, str)})
    if as_files:
        raise BadRequestError(f"form fields {as_files} were sent as files; send them as text fields (curl: "
                              f"-F name=value, not -F name=@file); only {sorted(file_fields)} are files")


def refuse_files_sent_as_text(form: FormData, files: Iterable[str]) -> None:
    """400 naming the file fields that arrived as text (``-F scan=<file.png`` or ``-F map_file=name``: the text
    of the part, not a file): said plainly instead of a validation error about Python types."""
    file_fields = set(files)
    # an empty value is "not given" (a script that always sends every field), as FastAPI reads it
    as_text = sorted({k for k, v in form.multi_items() if k in file_fields and isinstance(v, str) and v != ""})
    if as_text:
        raise BadRequestError(f"{', '.join(repr(k) for k in as_text)} arrived as text; send "
                              f"{'it as a file' if len(as_text) == 1 else 'them as files'} "
                              f"(curl: -F {as_text[0]}=@path, not -F {as_text[0]}=value or -F {as_text[0]}=<path)")


class _DuplicateKeysError(ValueError):
    """A JSON object names a key twice (raised by ``_pairs_without_duplicates``)."""

    def __init__(self, keys: list[str]) -> None:
        super().__init__(keys)
        self.keys = keys


def _pairs_without_duplicates(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    found = dict(pairs)
    if len(found) != len(pairs):
        raise _DuplicateKeysError(sorted(k for k, n in Counter(k for k, _ in pairs).items() if n > 1))
    return found


def _body_errors(exc: ValidationError) -> list[Any]:
    """``exc``'s errors located as FastAPI locates a request body's (``["body", "top_k"]``), so a field's error
    reads the same whether the scan came inline (multipart) or by ``scan_id`` (JSON), and on every route."""
    return [{**e, "loc": ("body", *e["loc"])} for e in exc.errors(include_url=False)]


#: Unknown fields of a JSON body reported one by one; a body with more is refused by count: the validator
#: builds an error per unknown key, and 400,000 keys (4.7 MB) took 7 s and 550 MB to answer (QA, session 22)
MAX_UNKNOWN_JSON_FIELDS = 20


def validate_json_body(raw: bytes, json_model: type[BaseModel]) -> BaseModel:
    """``raw`` (a JSON request body) validated strictly as ``json_model``.

    A JSON object with more than ``MAX_UNKNOWN_JSON_FIELDS`` keys the model does not have is refused before
    validation, by a plain parse (the validator would list each). Then duplicate keys are refused
    (``refuse_duplicate_json_keys``).

    Raises:
        RequestValidationError (422): invalid body, or too many unknown fields. BadRequestError (400): a key
        given twice.
    """
    parsed = None
    if raw.count(b":") > MAX_UNKNOWN_JSON_FIELDS:  # every key needs a colon: an ordinary body is not parsed twice
        try:
            parsed = from_json(raw)
        except ValueError:  # invalid JSON, or too deep: the validator says so, cheaply
            parsed = None
    if isinstance(parsed, dict):
        names = json_model.model_fields  # once: a property that builds its dict on every access
        unknown = [k for k in parsed if k not in names]
        if len(unknown) > MAX_UNKNOWN_JSON_FIELDS:
            raise RequestValidationError([{
                "loc": ("body",), "type": "extra_forbidden",
                "msg": f"{len(unknown):,} unknown fields (e.g. {', '.join(repr(k[:40]) for k in unknown[:3])}); "
                       f"the body takes {', '.join(names)}"}])
    try:
        model = json_model.model_validate_json(raw or b"{}", strict=True)
    except ValidationError as exc:
        raise RequestValidationError(_body_errors(exc)) from None
    refuse_duplicate_json_keys(raw)  # the validator keeps a repeated key's last value
    return model


def refuse_duplicate_json_keys(raw: bytes) -> None:
    """400 when the JSON body ``raw`` names a key twice in one object (``{"map_id": "a", "map_id": "b"}``): JSON
    parsers keep the last silently, which would localize on a map the client may not have meant. A body that is
    no valid JSON passes here (the model's strict validation refuses it). Called once the body has validated:
    then it is one flat object of the model's fields, so this second parse is cheap, where a hostile body of
    millions of nested objects would cost a Python call each."""
    try:
        json.loads(raw, object_pairs_hook=_pairs_without_duplicates)
    except _DuplicateKeysError as exc:
        raise BadRequestError(f"JSON fields {exc.keys} are given more than once; send each field once") from None
    except (ValueError, RecursionError):  # invalid JSON / UTF-8, digits beyond int's limit, deep nesting
        return


async def read_multipart_form(request: Request, max_files: int, max_fields: int) -> FormData:
    """The request's multipart/form-data body parsed as ``request.form`` does, refusing a body that does not end
    with the closing delimiter (``--boundary--``): the multipart parser drops the part that was still open
    without a word, so a scan sent last was reported missing ("needs a file field named 'scan'") although it was
    there. The delimiter is looked for in the stream as it is parsed (no copy of the body).

    Raises:
        BadRequestError (400): a malformed body, or one without its closing delimiter.
    """
    _, params = parse_options_header(request.headers.get("content-type", ""))  # as the parser reads it
    boundary = params.get(b"boundary", b"")
    closing = b"\r\n--" + boundary + b"--"
    closed = False

    async def stream() -> AsyncGenerator[bytes, None]:
        nonlocal closed
        tail = b"\r\n"  # the body's first delimiter has no CRLF before it
        async for chunk in request.stream():
            if not closed and chunk:
                # the delimiter may straddle two chunks; it cannot occur inside a part (it would end the part)
                closed = closing in tail + chunk[:len(closing)] or closing in chunk
                tail = (tail + chunk[-len(closing):])[-len(closing):]
            yield chunk

    try:
        async with aclosing(stream()) as body:
            form = await MultiPartParser(request.headers, body, max_files=max_files, max_fields=max_fields).parse()
    except Exception as exc:  # noqa: BLE001 - the multipart parser raises several types on bad input
        raise BadRequestError(f"malformed multipart body ({exc})") from exc
    if not closed and boundary:
        await form.close()
        raise BadRequestError("malformed multipart body (no closing boundary: the body must end with "
                              "--<boundary>--, the boundary of its Content-Type); send the whole body")
    return form


class ClosedFormRoute(APIRoute):
    """An ``APIRoute`` whose form parameters (``Form`` / ``File``) are read by ``read_multipart_form``, so that a
    multipart body without its closing delimiter is a 400 saying so on ``POST /maps`` and ``POST /scans`` too,
    as it is on ``/localize``: FastAPI's own parse drops the part still open and then reports a file it dropped
    as missing. The form is parsed here, before FastAPI reads the body, and left where ``request.form()``
    returns it (Starlette keeps one parse per request). Routes without form parameters are unchanged."""

    #: enough for every form route here (at most four fields and three files); a body with more parts is
    #: refused as malformed before its parts are spooled, with the count in the message
    MAX_PARTS = 16

    def get_route_handler(self) -> Any:
        handler = super().get_route_handler()
        if self.body_field is None or not isinstance(self.body_field.field_info, params.Form):
            return handler

        files = tuple(f.alias for f in self.dependant.body_params if isinstance(f.field_info, params.File))

        async def parse_closed_form_first(request: Request) -> Any:
            ctype = request.headers.get("content-type", "").split(";")[0].strip().lower()
            if ctype == "multipart/form-data":
                request._form = await read_multipart_form(request, max_files=self.MAX_PARTS,
                                                          max_fields=self.MAX_PARTS)
                refuse_files_sent_as_text(request._form, files)
            elif ctype == "application/x-www-form-urlencoded" and files:
                refuse_files_sent_as_text(await request.form(), files)
            return await handler(request)

        return parse_closed_form_first


@dataclass
class ScanInput:
    """The request's scan features plus its other fields (validated by the route's model)."""

    features: ScanFeatures
    scan_id: str | None
    fields: dict[str, Any]
    timings_ms: dict[str, float] = field(default_factory=dict)
    #: the scan's far-view features, computed on first call (inline scans, when the service has a far view; a
    #: cached ``scan_id``'s when they were computed at upload, ``CachedScan.far_features``), or None
    far_features: Callable[[], ScanFeatures] | None = None
    #: the scan's far-view dense image (``matching.dense.dense_image``), computed on first call (inline scans on a
    #: service with a far view; a cached ``scan_id``'s when it was made at upload, ``CachedScan.dense_image``), or None
    dense_image: Callable[[], np.ndarray] | None = None


def scan_request_body(json_model: type[BaseModel], form_fields: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """OpenAPI ``requestBody`` documenting both encodings (for ``openapi_extra``)."""
    props: dict[str, Any] = {"scan": {"type": "string", "format": "binary",
                                      "description": "Navtech polar PNG or .npy array (see scan_layout)"}}
    props.update(form_fields)
    props["preset"] = {"type": "string", "enum": sorted(PRESETS),
                       "description": "Radar preset (default: the map's when the scan's bin count fits it, "
                                      "else inferred from the PNG's bin count; a polar .npy: the map's)"}
    props["scan_layout"] = SCAN_LAYOUT_SCHEMA
    required = ["scan"] + [k for k, v in form_fields.items() if v.pop("x-required", False)]
    return {"requestBody": {"required": True, "content": {
        "application/json": {"schema": json_model.model_json_schema()},
        "multipart/form-data": {"schema": {"type": "object", "properties": props, "required": required}},
    }}}


async def read_scan_input(request: Request, state: ServiceState, json_model: type[BaseModel],
                          form_keys: tuple[str, ...], map_id: str | None = None) -> ScanInput:
    """Features of the request's scan and its validated fields.

    JSON bodies are validated with ``json_model`` and must name a cached ``scan_id``; multipart bodies carry a
    ``scan`` file (decoded and described here) and the fields in ``form_keys``. The map is ``map_id`` (a path
    parameter) or the body's ``map_id`` field: an inline scan without a preset takes its geometry, a cached one
    whose preset was a guess is checked against it (``ServiceState.check_cached_preset``).

    Raises:
        RequestValidationError (422), NotFoundError (404, unknown/expired scan id), ScanFormatError (422),
        UnsupportedMediaError (415).
    """
    ctype = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if ctype == "application/json":
        raw = await request.body()
        # off the event loop: a hostile body of the size limit costs a parse (health checks stay fast)
        model = await run_in_threadpool(validate_json_body, raw, json_model)
        fields = model.model_dump()
        scan_id = fields.pop("scan_id")
        # the uploader's own scans only (``ScanCache``); Redis in fleet mode: never on the event loop
        cached = await run_in_threadpool(state.cache.get, scan_id, caller_of(request))
        if cached is None:
            raise NotFoundError(f"unknown or expired scan_id {scan_id!r}; upload the scan again with POST /scans")
        target = map_id or fields.get("map_id")
        if target:
            state.check_cached_preset(scan_id, cached.preset, cached.preset_open, target)
        far = cached.far_features  # computed at upload while a map had a far-view companion, else None
        dense = cached.dense_image  # ... and its dense image while one held dense images, else None
        return ScanInput(cached.features, scan_id, fields, far_features=None if far is None else (lambda: far),
                         dense_image=None if dense is None else (lambda: np.asarray(dense, np.float32)))
    if ctype == "multipart/form-data":
        # two files, so that a repeated `scan` gets the "given more than once" answer below (the body is bounded)
        form = await read_multipart_form(request, max_files=2, max_fields=16)
        refuse_repeated_fields(form)
        refuse_text_fields_sent_as_files(form, ("scan",))
        refuse_files_sent_as_text(form, ("scan",))
        upload = form.get("scan")
        if not isinstance(upload, UploadFile):
            raise BadRequestError("multipart request needs a file field named 'scan' (a Navtech PNG or .npy)")
        raw_fields: dict[str, Any] = {k: v for k, v in form.items()
                                      if k in form_keys and isinstance(v, str) and v != ""}
        if "top_k" in raw_fields:  # form fields are text: only plain decimal integers ("true", "5.0" are not)
            if not _TOP_K_FORM.fullmatch(raw_fields["top_k"]):
                raise RequestValidationError([{"loc": ("body", "top_k"), "msg": "Input should be a decimal integer",
                                               "type": "int_parsing"}])
            raw_fields["top_k"] = int(raw_fields["top_k"])
        for name, text in list(raw_fields.items()):  # numeric form fields (tracking): plain finite decimals
            info = json_model.model_fields.get(name)
            if info is None or name == "top_k" or float not in getattr(info.annotation, "__args__", (info.annotation,)):
                continue
            value = float(text) if _FLOAT_FORM.fullmatch(text) else math.nan
            if not math.isfinite(value):
                raise RequestValidationError([{"loc": ("body", name), "msg": "Input should be a finite decimal number",
                                               "type": "float_parsing"}])
            raw_fields[name] = value
        refuse_unknown_fields(form, ("scan", "preset", "scan_layout", *form_keys))
        scan_layout = parse_scan_layout(form.get("scan_layout"))
        preset = form.get("preset")
        preset = preset if isinstance(preset, str) and preset else None
        if preset is not None and preset.lower() not in PRESETS:
            raise BadRequestError(f"unknown preset {shorten_echo(preset)!r}; choose one of {sorted(PRESETS)}")
        try:
            model = json_model.model_validate({"scan_id": "inline", **raw_fields}, strict=True)
        except ValidationError as exc:
            raise RequestValidationError(_body_errors(exc)) from None
        fields = model.model_dump()
        fields.pop("scan_id")
        data, filename = await read_scan_upload(upload, state.settings.max_scan_pixels, scan_layout)
        timings: dict[str, float] = {}
        features, _, _, scan = await run_in_threadpool(state.describe_upload, data, filename, preset, timings,
                                                       scan_layout, map_id or fields.get("map_id"))
        return ScanInput(features, None, fields, timings, state.far_features_of(scan, timings),
                         state.dense_image_of(scan, timings))
    raise UnsupportedMediaError(
        f"unsupported Content-Type {ctype or '(none)'!r}: send application/json with a scan_id or "
        f"multipart/form-data with a 'scan' file"
    )

