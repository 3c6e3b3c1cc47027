"""Service-level errors (unknown ids, conflicts, auth, size); mapped to HTTP codes in ``service.main``."""

from __future__ import annotations

__all__ = ["ServiceError", "NotFoundError", "ConflictError", "PayloadTooLargeError", "BadRequestError",
           "ServiceUnavailableError", "UnauthorizedError"]


class ServiceError(Exception):
    """Base class; ``status_code`` and ``code`` go into the JSON error body."""

    status_code = 400
    code = "bad_request"

    def __init__(self, message: str) -> None:
        super().__init__(message)
        self.message = message


class BadRequestError(ServiceError):
    status_code = 400
    code = "bad_request"


class NotFoundError(ServiceError):
    status_code = 404
    code = "not_found"


class ConflictError(ServiceError):
    status_code = 409
    code = "conflict"


class PayloadTooLargeError(ServiceError):
    status_code = 413
    code = "payload_too_large"


class ServiceUnavailableError(ServiceError):
    status_code = 503
    code = "not_ready"


class UnauthorizedError(ServiceError):
    status_code = 401
    code = "unauthorized"
