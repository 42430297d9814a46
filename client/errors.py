"""Typed errors raised by the SDK, each carrying the server's own message.

HTTP failures map by status code (`error_for_status`); WebSocket error frames become `StreamError` (or
`BackpressureError` when the client gave up re-sending a refused frame).
"""

from __future__ import annotations

from typing import Any


class FlashMonoError(Exception):
    """Base class of every SDK error. `status_code` is the HTTP status when there was one."""

    def __init__(self, message: str, *, status_code: int | None = None, detail: Any = None) -> None:
        super().__init__(message)
        self.message = message
        self.status_code = status_code
        self.detail = detail if detail is not None else message

    def __str__(self) -> str:
        return f"[{self.status_code}] {self.message}" if self.status_code else self.message


class BadRequestError(FlashMonoError):
    """400/413/415/422: the request was malformed or its values were rejected."""


class AuthError(FlashMonoError):
    """401: the API key is missing or unknown."""


class PermissionDeniedError(FlashMonoError):
    """403: the key is valid but lacks the scope, or the session belongs to someone else."""


class NotFoundError(FlashMonoError):
    """404: no such session (or route)."""


class ConflictError(FlashMonoError):
    """409: the request conflicts with the session's state (e.g. rendering before any keyframe)."""


class RateLimitError(FlashMonoError):
    """429: too many requests; retry later."""


class ServerError(FlashMonoError):
    """5xx: the service failed or is unavailable."""


class ServerUnreachableError(FlashMonoError):
    """The server could not be reached at all (connection refused, DNS, timeout)."""


class StreamError(FlashMonoError):
    """An error frame on the WebSocket, or the stream closed unexpectedly. `code` is the server's error code."""

    def __init__(self, message: str, *, code: str = "stream_error", seq: int | None = None, **kwargs: Any) -> None:
        super().__init__(message, **kwargs)
        self.code = code
        self.seq = seq

    def __str__(self) -> str:
        where = f" (seq {self.seq})" if self.seq is not None else ""
        return f"{self.code}: {self.message}{where}"


class BackpressureError(StreamError):
    """The server kept refusing a frame because its queue stayed full, beyond the client's retry budget."""


_BY_STATUS: dict[int, type[FlashMonoError]] = {
    400: BadRequestError,
    401: AuthError,
    403: PermissionDeniedError,
    404: NotFoundError,
    409: ConflictError,
    413: BadRequestError,
    415: BadRequestError,
    422: BadRequestError,
    429: RateLimitError,
}


def _message_from_body(body: Any, fallback: str) -> tuple[str, Any]:
    """The human message of an error body: FastAPI's {"detail": str | [validation errors]} or plain text."""
    if isinstance(body, dict) and "detail" in body:
        detail = body["detail"]
        if isinstance(detail, str):
            return detail, detail
        if isinstance(detail, list):  # pydantic validation errors
            parts = []
            for item in detail:
                if isinstance(item, dict):
                    loc = ".".join(str(p) for p in item.get("loc", ()) if p != "body")
                    parts.append(f"{loc}: {item.get('msg', item)}" if loc else str(item.get("msg", item)))
                else:
                    parts.append(str(item))
            return "; ".join(parts) or fallback, detail
        return str(detail), detail
    if isinstance(body, str) and body.strip():
        return body.strip()[:500], body
    return fallback, body


def error_for_status(status_code: int, body: Any, reason: str = "") -> FlashMonoError:
    """The typed error for an HTTP failure `status_code` with decoded `body` (JSON object or text)."""
    fallback = f"HTTP {status_code} {reason}".strip()
    message, detail = _message_from_body(body, fallback)
    if status_code >= 500:
        cls: type[FlashMonoError] = ServerError
    else:
        cls = _BY_STATUS.get(status_code, FlashMonoError)
    return cls(message, status_code=status_code, detail=detail)


def stream_error_from_frame(frame: dict[str, Any]) -> StreamError:
    """A `StreamError` built from a server error frame {type: "error", code, message, seq?}."""
    code = str(frame.get("code") or "stream_error")
    message = str(frame.get("message") or frame.get("detail") or code)
    seq = frame.get("seq")
    cls = BackpressureError if code == "backpressure" else StreamError
    return cls(message, code=code, seq=int(seq) if isinstance(seq, int) else None, detail=frame)
