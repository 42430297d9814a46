"""Checks of our own for the schemathesis run (loaded through SCHEMATHESIS_HOOKS by test_schemathesis.py)."""

from __future__ import annotations

import schemathesis

# render_params's refusal of a pose that is not 16 comma-separated numbers: the schema's `pattern` says the same,
# so a request generated from the schema (positive data) never gets it
POSE_SYNTAX_REFUSAL = "pose must be 16 comma-separated"


@schemathesis.check
def render_pose_syntax_is_the_schemas(ctx, response, case):
    """A render pose the schema accepts is never refused for its syntax (only for what it means: not rigid)."""
    meta = case.meta
    if meta is None or not meta.generation.mode.is_positive or response.status_code != 400:
        return None
    if not case.operation.path.endswith("/render"):
        return None
    try:
        detail = str(response.json().get("detail", ""))
    except ValueError:
        return None
    if POSE_SYNTAX_REFUSAL in detail:
        raise AssertionError(f"the server refused a pose its schema accepts ({case.query.get('pose')!r}): {detail}")
    return None
