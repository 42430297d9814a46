"""HTTP failures and WebSocket error frames become typed SDK errors carrying the server's message."""

from __future__ import annotations

import pytest

from client.errors import (
    AuthError,
    BackpressureError,
    BadRequestError,
    ConflictError,
    FlashMonoError,
    NotFoundError,
    PermissionDeniedError,
    RateLimitError,
    ServerError,
    StreamError,
    error_for_status,
    stream_error_from_frame,
)


@pytest.mark.parametrize(
    ("status", "cls"),
    [(400, BadRequestError), (401, AuthError), (403, PermissionDeniedError), (404, NotFoundError),
     (409, ConflictError), (413, BadRequestError), (422, BadRequestError), (429, RateLimitError),
     (500, ServerError), (503, ServerError), (418, FlashMonoError)],
)
def test_status_codes_map_to_typed_errors(status: int, cls: type) -> None:
    err = error_for_status(status, {"detail": "the server said so"})
    assert type(err) is cls
    assert err.status_code == status
    assert err.message == "the server said so"
    assert "the server said so" in str(err)


def test_validation_error_lists_are_joined_with_their_fields() -> None:
    body = {"detail": [{"loc": ["body", "intrinsics", "fx"], "msg": "Input should be greater than 0"},
                       {"loc": ["query", "limit"], "msg": "Input should be a valid integer"}]}
    err = error_for_status(422, body)
    assert isinstance(err, BadRequestError)
    assert "intrinsics.fx: Input should be greater than 0" in err.message
    assert "query.limit: Input should be a valid integer" in err.message
    assert err.detail == body["detail"]


def test_plain_text_and_empty_bodies_still_give_a_message() -> None:
    assert error_for_status(502, "Bad gateway from proxy").message == "Bad gateway from proxy"
    assert error_for_status(500, "", "Internal Server Error").message == "HTTP 500 Internal Server Error"


def test_stream_error_frames() -> None:
    err = stream_error_from_frame({"type": "error", "code": "bad_image", "message": "cannot decode JPEG", "seq": 7})
    assert type(err) is StreamError
    assert (err.code, err.seq, err.message) == ("bad_image", 7, "cannot decode JPEG")
    assert "seq 7" in str(err)
    full = stream_error_from_frame({"type": "error", "code": "backpressure", "message": "queue full", "seq": 3})
    assert isinstance(full, BackpressureError) and isinstance(full, StreamError)
    bare = stream_error_from_frame({"type": "error"})
    assert bare.code == "stream_error" and bare.seq is None
