"""The WebSocket protocol, as the `x-websocket` extension of openapi.yaml (OpenAPI cannot describe WebSockets)."""

from __future__ import annotations

_POSE = {"type": "array", "items": {"type": "number"}, "minItems": 16, "maxItems": 16,
         "description": "camera-to-world 4x4, row-major"}

WEBSOCKET_DOC = {
    "/v1/sessions/{session_id}/stream": {
        "summary": "Stream camera frames; receive acks, live poses and loop-closure events",
        "auth": "X-API-Key or Authorization: Bearer header, or ?api_key= query parameter; needs the stream scope "
                "and the key that created the session (or admin). Failures: an error message with code "
                "unauthorized/forbidden/not_found, then close code 4401/4403/4404.",
        "client_messages": {
            "frame": {
                "encoding": "binary msgpack map",
                "schema": {
                    "type": "object", "required": ["type", "seq", "timestamp", "image"],
                    "properties": {
                        "type": {"const": "frame"},
                        "seq": {"type": "integer", "minimum": 0,
                                "description": "strictly increasing; duplicates and out-of-order frames are refused"},
                        "timestamp": {"type": "number", "description": "seconds"},
                        "image": {"type": "string", "format": "binary", "description": "JPEG or PNG (RGB)"},
                        "intrinsics": {"description": "overrides the session's intrinsics for this frame",
                                       "oneOf": [{"type": "object", "required": ["fx", "fy", "cx", "cy"]},
                                                 {"type": "array", "items": {"type": "number"}, "minItems": 4,
                                                  "maxItems": 4}]},
                        "depth": {"type": "string", "format": "binary",
                                  "description": "16-bit single-channel PNG in millimetres, same size as the image"},
                        "pose": {**_POSE, "description": "device pose prior, camera-to-world 4x4 row-major"},
                    },
                },
            },
            "finish": {"encoding": "text JSON",
                       "schema": {"type": "object", "properties": {"type": {"const": "finish"}}},
                       "description": "no more frames: the worker finishes the map (with the preset's final "
                                      "refinement over every keyframe, if it has one: tens of seconds for `rgbd`; "
                                      "render requests are answered after it); the server sends finished, then "
                                      "closes (code 1000)"},
            "ping": {"encoding": "text JSON", "schema": {"type": "object", "properties": {"type": {"const": "ping"}}},
                     "description": "answered by {type: pong}"},
        },
        "server_messages": {
            "encoding": "text JSON",
            "ack": {"type": "object", "properties": {
                "type": {"const": "ack"}, "seq": {"type": "integer"},
                "queue_depth": {"type": "integer", "description": "frames queued for the worker, this one included"}},
                "description": "the frame is queued (durably, in Redis)"},
            "pose": {"type": "object", "properties": {
                "type": {"const": "pose"}, "seq": {"type": "integer"}, "timestamp": {"type": "number"},
                "pose": _POSE, "is_keyframe": {"type": "boolean"}, "revision": {"type": "integer"}},
                "description": "the tracked pose of a frame; sent once per seq"},
            "loop_closed": {"type": "object", "properties": {
                "type": {"const": "loop_closed"}, "revision": {"type": "integer"}},
                "additionalProperties": True,
                "description": "a loop closure rewrote past poses: GET the trajectory for revision `revision`"},
            "error": {"type": "object", "properties": {
                "type": {"const": "error"}, "seq": {"type": "integer"}, "message": {"type": "string"},
                "code": {"enum": ["backpressure", "bad_seq", "bad_message", "bad_image", "bad_depth", "bad_pose",
                                  "bad_intrinsics", "bad_frame", "too_large", "not_accepting", "not_found",
                                  "unauthorized", "forbidden", "engine_failed"]},
                "queue_depth": {"type": "integer", "description": "with backpressure"}},
                "description": "a refused frame (never silently dropped: backpressure means resend later) or a "
                               "session-level problem; the stream stays open except for not_found/auth errors"},
            "finished": {"type": "object", "properties": {
                "type": {"const": "finished"}, "frames": {"type": "integer", "description": "frames processed"}}},
            "pong": {"type": "object", "properties": {"type": {"const": "pong"}}},
        },
        "limits": "frame messages up to FLASHMONO_MAX_FRAME_BYTES (8 MiB); at most FLASHMONO_MAX_QUEUE (64) frames "
                  "queued per session",
    }
}
