"""The exceptions of horizon_bake: one class per kind of failure, for the library and the client.

The native bake raises them with the message the CLI prints after ``horizon-bake:``; the client
raises them from the service's problem+json (``detail`` as the message). ``code`` is the
problem+json ``code`` in both cases, ``field`` the parameter a ParameterError is about.
"""

from __future__ import annotations

from typing import Optional


class HorizonBakeError(Exception):
    """Any failure of a bake or of the service."""

    def __init__(self, message: str, *, code: Optional[str] = None, field: Optional[str] = None,
                 status: Optional[int] = None):
        super().__init__(message)
        self.message = message
        self.code = code
        self.field = field
        self.status = status


class ParameterError(HorizonBakeError, ValueError):
    """A parameter is unknown, malformed or out of range; ``field`` names it as SPEC spells it."""


class InputError(HorizonBakeError, ValueError):
    """The heights cannot be baked: not an image, broken, non-finite values, every texel nodata."""


class LimitError(HorizonBakeError):
    """The input is over a limit (dimensions, bytes, memory)."""


class Canceled(HorizonBakeError):
    """The bake was canceled (a progress callback returned False, Ctrl-C, or DELETE)."""


class NotFound(HorizonBakeError, LookupError):
    """The service has no such bake or result."""


class ServiceError(HorizonBakeError):
    """The service failed or stayed unavailable after the client's retries."""


#: problem+json ``code`` → class, for the client.
BY_CODE = {
    "invalid_parameter": ParameterError,
    "unknown_parameter": ParameterError,
    "decode_failed": InputError,
    "unsupported_media_type": InputError,
    "invalid_input": InputError,
    "payload_too_large": LimitError,
    "dimensions_too_large": LimitError,
    "decode_memory_busy": LimitError,
    "canceled": Canceled,
    "bake_not_found": NotFound,
    "result_not_found": NotFound,
    "queue_full": ServiceError,
    "shutting_down": ServiceError,
}
