"""The WebSocket protocol, as the `x-websocket` extension of openapi.yaml (OpenAPI cannot describe WebSockets).

A client written from this text alone must be able to stream without probing the server: every message, error
code, close code, the flow-control rules and the session's lifetime are stated here.
"""

from __future__ import annotations

_POSE = {"type": "array", "items": {"type": "number"}, "minItems": 16, "maxItems": 16,
         "description": "camera-to-world similarity [sR | t; 0 0 0 1], 16 floats row-major (OpenCV camera: x right, "
                        "y down, z forward). The 3x3 block is s times a rotation: divide it by `scale` before "
                        "converting it to a quaternion. s = 1 with metric input (depth or device poses)"}
_SCALE = {"type": "number", "description": "s of the similarity: cbrt(|det(3x3 block)|)"}

FRAME_ERROR_CODES = {
    "backpressure": "the session's queue is full (or an earlier frame was refused for it): not queued; re-send "
                    "from `resend_from`",
    "unavailable": "the session store (Redis) is unreachable: not queued; re-send from `resend_from` (with a seq) "
                   "or reconnect (without)",
    "bad_seq": "seq not greater than the last accepted one (duplicate or out of order): not queued; the message "
               "names the last accepted seq",
    "bad_size": "the image's size differs from the session's first frame's: not queued (one size per session)",
    "bad_message": "not a msgpack map with type frame, a text frame, a bad seq/timestamp, or an unknown control "
                   "message",
    "bad_image": "image missing, not JPEG/PNG, too large a side, or corrupt (the last found by the worker after the "
                 "ack)",
    "bad_depth": "depth is not a 16-bit PNG of the image's size",
    "bad_pose": "pose is not 16 finite floats of a rigid or similarity transform",
    "bad_intrinsics": "intrinsics malformed, or the session's are for another aspect ratio",
    "too_large": "the message exceeds FLASHMONO_MAX_FRAME_BYTES",
    "bad_frame": "the worker could not use an acked frame (the engine refused it)",
    "not_accepting": "the session is finishing or finished: not queued",
    "too_many_streams": "this gateway holds FLASHMONO_MAX_STREAMS open streams: retry shortly (then close 1013)",
    "not_found": "the session was deleted (then close 4404)",
    "unauthorized": "missing or unknown API key (then close 4401)",
    "forbidden": "the key lacks the stream scope or did not create the session (then close 4403)",
    "forbidden_origin": "a browser Origin not in FLASHMONO_ALLOWED_ORIGINS (then close 4403)",
    "engine_failed": "the session failed in the worker (status failed)",
    "abandoned": "no frame for FLASHMONO_IDLE_TIMEOUT_S (600 s): the session is abandoned and its worker slot freed; "
                 "opening its stream again within FLASHMONO_ABANDONED_GRACE_S (3600 s) resumes it",
}

CLOSE_CODES = {
    "1000": "after `finished`: every frame was processed",
    "1009": "a message larger than the server's WebSocket limit (about 2 x FLASHMONO_MAX_FRAME_BYTES); no error "
            "frame (the WebSocket layer closes)",
    "1013": "try again later: the session store (Redis) is unreachable at connect time, or the gateway holds its "
            "FLASHMONO_MAX_STREAMS open streams",
    "4401": "unauthorized: missing or unknown key (header, or ?api_key=)",
    "4403": "forbidden: the key lacks the stream scope, did not create the session, or the Origin is not allowed",
    "4404": "the session does not exist or was deleted",
    "4409": "the session takes no frames (finishing, finished or failed)",
}

WEBSOCKET_DOC = {
    "/v1/sessions/{session_id}/stream": {
        "summary": "Stream camera frames; receive acks, live poses and loop-closure events",
        "auth": "X-API-Key or Authorization: Bearer header, or ?api_key= query parameter; needs the stream scope "
                "and the key that created the session (or admin). A server started without keys "
                "(FLASHMONO_API_KEYS unset) is open to anyone and logs a warning saying so at start-up.",
        "closing": "Every close other than 1000 and 1009 comes right after an `error` message with a `code` and a "
                   "`message` saying why. Close codes: see close_codes.",
        "close_codes": CLOSE_CODES,
        "flow_control": (
            "Each binary frame gets exactly one immediate answer, in the order frames arrived: `ack` (queued "
            "durably) or `error` with its seq (not queued, or unusable). Each acked frame later gets exactly one "
            "result with its seq: `pose` (processed) or `error` (the worker could not use it). A windowed sender "
            "therefore counts frames at the server as acks minus results, and frames on the wire as sent minus "
            "immediate answers; neither count can stall. Backpressure keeps the order: once frame N is refused "
            "with `backpressure`, every later seq is refused the same way with `resend_from: N`, even after the "
            "queue drains, until a frame with seq <= N is accepted; so rewind to N, wait a little (back off "
            "exponentially while refusals go on) and re-send from there, ignoring the refusals of frames sent "
            "before the rewind. A live camera that prefers fresh images may send its newest image under seq N."),
        "sequence_numbers": "seq must increase strictly within a session; gaps are allowed (a skipped seq is never "
                            "waited for). A seq at or below the last accepted one is refused with bad_seq.",
        "session_lifetime": (
            "Closing the socket without `finish` leaves the session live (status streaming) with its queue and "
            "results; nothing times it out. Reconnect to the same URL and go on with seqs above the last acked one "
            "(a bad_seq error names it); results already sent are not repeated, GET the trajectory for them. "
            "`finish` (from any connection) ends it; DELETE /v1/sessions/{id} discards it."),
        "client_messages": {
            "frame": {
                "encoding": "binary WebSocket message holding a msgpack map (text JSON frames are refused with "
                            "bad_message)",
                "schema": {
                    "type": "object", "required": ["type", "seq", "timestamp", "image"],
                    "properties": {
                        "type": {"const": "frame"},
                        "seq": {"type": "integer", "minimum": 0,
                                "description": "strictly increasing, gaps allowed; see sequence_numbers"},
                        "timestamp": {"type": "number", "description": "seconds"},
                        "image": {"type": "string", "format": "binary",
                                  "description": "JPEG or PNG (RGB) as raw bytes; every frame of a session the "
                                                 "same size"},
                        "intrinsics": {"description": "overrides the session's intrinsics for this frame",
                                       "oneOf": [{"type": "object", "required": ["fx", "fy", "cx", "cy"]},
                                                 {"type": "array", "items": {"type": "number"}, "minItems": 4,
                                                  "maxItems": 4}]},
                        "depth": {"type": "string", "format": "binary",
                                  "description": "16-bit single-channel PNG in millimetres, same size as the image "
                                                 "(0 = no depth)"},
                        "pose": {**_POSE, "description": "device pose, camera-to-world 4x4 row-major (rigid, metres); "
                                                         "the session's pose_mode says how it is used"},
                    },
                },
                "input_mode": "the fields of the first frame choose the input mode for the session (see the "
                              "`preset` field of POST /v1/sessions and GET /v1/presets)",
            },
            "finish": {"encoding": "text JSON",
                       "schema": {"type": "object", "properties": {"type": {"const": "finish"}}},
                       "description": "no more frames: the worker processes what is queued, then finishes the map "
                                      "with the preset's final refinement, if it has one, and sends finished and "
                                      "closes (code 1000); render requests are answered after it. `rgbd` refines 8 "
                                      "passes over every held keyframe (at most 66: the window and 64 archived), "
                                      "about 0.1 s per keyframe and pass at 320x240 on 2 CPU cores: 30 s for the "
                                      "211-frame ICL sequence (36 keyframes), up to about a minute for long "
                                      "sessions (bench/RESULTS.md). Meanwhile `finishing` messages come every 2 s "
                                      "and the session's status stays `finishing`"},
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
                "pose": _POSE, "scale": _SCALE, "is_keyframe": {"type": "boolean"}, "revision": {"type": "integer"}},
                "description": "the tracked pose of a frame: its result, sent once per seq"},
            "skipped": {"type": "object", "properties": {
                "type": {"const": "skipped"}, "seq": {"type": "integer"},
                "reason": {"type": "string", "enum": ["overload"]}},
                "description": "the result of a frame the tracker skipped: it waited longer than the worker's skip "
                               "limit (FLASHMONO_SKIP_AFTER_MS, 100 ms) while a newer frame was waiting, so the newer "
                               "one was tracked instead (newest first wins, a few in a row at most); no pose comes "
                               "for this seq"},
            "loop_closed": {"type": "object", "properties": {
                "type": {"const": "loop_closed"}, "revision": {"type": "integer"}},
                "additionalProperties": True,
                "description": "a loop closure rewrote past poses: GET the trajectory for revision `revision`"},
            "tracking_lost": {"type": "object", "properties": {
                "type": {"const": "tracking_lost"}, "seq": {"type": "integer", "description": "the frame it is at"},
                "reason": {"type": "string"}},
                "additionalProperties": True,
                "description": "the pose source lost the camera (a black, textureless or blurred view, no depth, a "
                               "sudden jump): until `relocalized`, poses hold the last good one and no keyframes are "
                               "made; never a silent jump (seeded sessions with depth: poses follow the device's "
                               "motion and, once lost for `device_poses.resume_after_s`, the odometry restarts at the "
                               "device's pose: `relocalized` with method device_pose)"},
            "relocalized": {"type": "object", "properties": {
                "type": {"const": "relocalized"}, "seq": {"type": "integer"}},
                "additionalProperties": True,
                "description": "tracking is back at frame `seq`, placed against an earlier keyframe (`method`: how; "
                               "device_pose: a seeded session's odometry restarted where the device's pose says the "
                               "camera is)"},
            "initializing": {"type": "object", "properties": {
                "type": {"const": "initializing"}, "seq": {"type": "integer"}, "state": {"type": "string"},
                "reason": {"type": "string"}, "model": {"type": "string"}},
                "additionalProperties": True,
                "description": "RGB-only sessions: visual odometry is waiting to make its first map (`state` "
                               "waiting_for_parallax or rotation_only: the camera only turned, so poses carry its "
                               "orientation and hold the position; `model` homography or essential); sent when the "
                               "state changes, `initialized` follows"},
            "initialized": {"type": "object", "properties": {
                "type": {"const": "initialized"}, "seq": {"type": "integer"}, "revision": {"type": "integer"},
                "frames_revised": {"type": "integer"}},
                "additionalProperties": True,
                "description": "RGB-only sessions: visual odometry made its first map at frame `seq`; the frames "
                               "before it, sent at the first frame's pose, were re-estimated: GET the trajectory "
                               "for revision `revision`. After a `new_map` (`map` > 1), `registered_frames` are the "
                               "frames reported lost while it waited, now posed in the new map (they move with it "
                               "when a loop joins the maps)"},
            "new_map": {"type": "object", "properties": {
                "type": {"const": "new_map"}, "seq": {"type": "integer"}, "map": {"type": "integer"},
                "lost_frames": {"type": "integer"}},
                "additionalProperties": True,
                "description": "RGB-only sessions: after a loss nothing could bridge (a jump to an unseen view), "
                               "visual odometry begins map number `map` at the last pose, with the old map's scene "
                               "depth; `initializing` and `initialized` follow, and a `loop_closed` joining the two "
                               "maps moves it into place (a new trajectory revision)"},
            "rotation_only": {"type": "object", "properties": {
                "type": {"const": "rotation_only"}, "seq": {"type": "integer"},
                "tracks": {"type": "integer", "description": "tracks that agree on the rotation"},
                "map_points": {"type": "integer", "description": "map points that measured the position (0: held)"},
                "method": {"const": "photometric", "description": "present when no track survived (a fast turn "
                                                                  "over weak or striped texture): the turn comes "
                                                                  "from aligning the whole image, `quality` at "
                                                                  "most 0.4"},
                "correlation": {"type": "number"},
                "measured_axes": {"type": "integer", "description": "photometric: rotation axes the image measured "
                                                                    "(the others follow the predicted turn)"}},
                "additionalProperties": True,
                "description": "RGB-only sessions: a turn too fast for new points to be triangulated; from frame "
                               "`seq` the poses follow the rotation every track agrees on, the position from the "
                               "map points still seen (or held), with `quality` at most 0.5, until the tracks "
                               "measure map points again (no event: `quality` rises) or tracking is lost"},
            "maps_merged": {"type": "object", "properties": {
                "type": {"const": "maps_merged"}, "seq": {"type": "integer"}, "revision": {"type": "integer"},
                "place": {"type": "integer", "description": "the older frame the restarted map recognised"},
                "since": {"type": "integer", "description": "the first frame of the restarted map"},
                "scale": {"type": "number", "description": "how much the restarted map was scaled to fit"}},
                "additionalProperties": True,
                "description": "RGB-only sessions: a map visual odometry restarted after `tracking_lost` recognised "
                               "a place of the older map; a Sim(3) edge joined the two in the pose graph and the "
                               "restarted map's poses moved into the older map's frame, scale included: GET the "
                               "trajectory for revision `revision`"},
            "drift_corrected": {"type": "object", "properties": {
                "type": {"const": "drift_corrected"}, "seq": {"type": "integer"}, "revision": {"type": "integer"},
                "keyframe": {"type": "integer", "description": "the newest keyframe whose device pose was used"}},
                "additionalProperties": True,
                "description": "posed RGB sessions where the device poses seed visual odometry (pose_source "
                               "seeded): the pose graph was solved with the device's keyframe poses as priors, "
                               "correcting the odometry's drift (its scale above all) between loop closures; past "
                               "keyframes and their part of the map moved: GET the trajectory for revision "
                               "`revision`"},
            "poses_refined": {"type": "object", "properties": {
                "type": {"const": "poses_refined"}, "seq": {"type": "integer"}, "revision": {"type": "integer"},
                "keyframes": {"type": "integer", "description": "how many keyframes' cameras moved"}},
                "additionalProperties": True,
                "description": "sent once while a session finishes, before `finished`, when "
                               "`mapping.final_refine_poses` is on: the final refinement moved the keyframes' cameras "
                               "where the map's renders fit their photos (photometric bundle adjustment; never with "
                               "pose_mode fixed), every frame following its keyframe: GET the trajectory for "
                               "revision `revision`"},
            "device_pose_jump": {"type": "object", "properties": {
                "type": {"const": "device_pose_jump"}, "seq": {"type": "integer"},
                "translation": {"type": "number", "description": "how far the device's motion into this frame is "
                                                                 "from the tracked motion (pose units)"},
                "rotation_deg": {"type": "number"}},
                "additionalProperties": True,
                "description": "pose_mode seeded: the device pose of frame `seq` jumped (ARKit/ARCore relocalising, a "
                               "glitch); the session's poses do not follow the jump and the next keyframe gets no "
                               "device prior"},
            "pose_source_chosen": {"type": "object", "properties": {
                "type": {"const": "pose_source_chosen"}, "seq": {"type": "integer"},
                "pose_source": {"enum": ["prior", "seeded"]}, "reason": {"type": "string"},
                "reprojection_px": {"type": "number", "description": "median three-view reprojection error of "
                                                                     "tracked corners with the device's poses"},
                "fitted_px": {"type": "number", "description": "... with poses fitted to the same tracks"},
                "ratio": {"type": "number"}, "max_ratio": {"type": "number"},
                "triples": {"type": "integer", "description": "frame triples measured"},
                "agree": {"type": ["boolean", "null"], "description": "null: too few triples to judge by"},
                "frames_replayed": {"type": "integer", "description": "the judged frames, tracked again by the "
                                                                       "chosen source from the first"},
                "revision": {"type": "integer", "description": "the trajectory revision with their new poses"}},
                "additionalProperties": True,
                "description": "pose_mode auto, frames with poses and no depth: over the first frames (at most "
                               "input.pose_choice.within_frames, 30) the device poses were judged against the images "
                               "(meanwhile frames get the device's poses, provisionally, and no keyframe); "
                               "`prior`: they are the odometry; `seeded`: visual odometry tracks from the device's "
                               "motion, the device poses are pose-graph priors (also in the session's warnings); "
                               "either way the judged frames go through the chosen source from the first"},
            "odometry_slip": {"type": "object", "properties": {
                "type": {"const": "odometry_slip"}, "seq": {"type": "integer"},
                "photometric_rms": {"type": "array", "items": {"type": "number"},
                                    "description": "robust intensity residual of the odometry's pose, then of the "
                                                   "pose tracked again from the device's motion"},
                "geometric_rms": {"type": "array", "items": {"type": "number"}}},
                "additionalProperties": True,
                "description": "pose_mode seeded with depth: the device and the RGB-D odometry disagreed on frame "
                               "`seq` and the images sided with the device (the odometry had settled in a wrong "
                               "place): the frame was tracked again from the device's motion; no device jump"},
            "depth_misregistered": {"type": "object", "properties": {
                "type": {"const": "depth_misregistered"}, "seq": {"type": "integer"},
                "shift_dx": {"type": "integer"}, "shift_dy": {"type": "integer"}, "message": {"type": "string"}},
                "additionalProperties": True,
                "description": "sessions without depth_camera: over the first frames, depth edges fit colour edges "
                               "best shifted by (shift_dx, shift_dy) pixels: colour and depth are not registered "
                               "(also in the session's warnings); create the session with depth_camera"},
            "error": {"type": "object", "required": ["type", "code", "message"], "properties": {
                "type": {"const": "error"}, "seq": {"type": "integer", "description": "the frame it is about"},
                "message": {"type": "string"},
                "code": {"enum": list(FRAME_ERROR_CODES), "description": "; ".join(
                    f"{code}: {meaning}" for code, meaning in FRAME_ERROR_CODES.items())},
                "queue_depth": {"type": "integer", "description": "with backpressure"},
                "resend_from": {"type": "integer", "description": "with backpressure/unavailable: the seq to "
                                                                  "re-send next"}},
                "description": "a refused or unusable frame (never silently dropped) or a session-level problem; "
                               "the stream stays open except where close_codes says otherwise"},
            "finishing": {"type": "object", "properties": {
                "type": {"const": "finishing"}, "elapsed_s": {"type": "number", "description": "since finish began"},
                "phase": {"type": "string", "enum": ["mapping", "loop_closing", "refining", "done"],
                          "description": "mapping: the keyframes still waiting are mapped; loop_closing: the last "
                          "loop queries are answered; refining: the final refinement"},
                "done": {"type": "integer", "description": "work units of the phase done (keyframes, iterations)"},
                "total": {"type": "integer", "description": "work units of the phase in all"},
                "eta_s": {"type": "number", "description": "seconds the phase still needs at its pace so far "
                          "(bounded by the finish budget); absent until there is a pace"}},
                "description": "the worker is finishing the session (after the last queued frame): sent when it "
                               "starts and every 2 s until `finished`"},
            "finished": {"type": "object", "properties": {
                "type": {"const": "finished"}, "frames": {"type": "integer", "description": "frames processed"}}},
            "pong": {"type": "object", "properties": {"type": {"const": "pong"}}},
        },
        "limits": "frame messages up to FLASHMONO_MAX_FRAME_BYTES (8 MiB); at most FLASHMONO_MAX_QUEUE (64) frames "
                  "queued per session",
    },
    "/v1/sessions/{session_id}/events": {
        "description": "A read-only feed for viewers that do not send the frames (the web viewer): the messages the "
                       "session's stream gets (pose, loop_closed, maps_merged, drift_corrected, poses_refined, "
                       "tracking_lost, relocalized, initializing, initialized, new_map, rotation_only, "
                       "device_pose_jump, odometry_slip, pose_source_chosen, "
                       "depth_misregistered, "
                       "error, finishing, finished) "
                       "from the "
                       "moment of connection; the trajectory endpoint has the earlier ones. A session already "
                       "finished or failed answers one `finished`/`failed` message. Same authentication as the "
                       "stream (read or stream scope; ?api_key= allowed).",
        "client_messages": {},
        "server_messages": "as the stream's server_messages, without ack",
        "close_codes": {"1000": "after finished", "4401": "unknown or missing API key", "4403": "not allowed",
                        "4404": "no such session, or it was deleted"},
    },
}
