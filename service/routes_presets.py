"""GET /v1/presets: the engine presets a session can name, what each is for and which input suits it, and what
`auto` (no preset named) chooses on the live workers' machines."""

from __future__ import annotations

import json
from collections import Counter

from fastapi import APIRouter, Depends, Request

from service.auth import Principal, caller
from service.presets import INPUT_MODES, preset_list
from service.schemas import ErrorBody, PresetList
from worker.settings_choice import Machine, choices_by_input

router = APIRouter(prefix="/v1/presets", tags=["sessions"], responses={401: {"model": ErrorBody}})


@router.get("", response_model=PresetList)
async def list_presets(request: Request, principal: Principal = Depends(caller)) -> dict:
    """The presets for `POST /v1/sessions` (any valid key), how the input mode follows from a frame's fields, and
    what `auto` chooses per input mode on each kind of machine among the live workers."""
    kinds = Counter(json.dumps(m, sort_keys=True) for m in await request.app.state.registry.worker_machines())
    choices = []
    for text, workers in sorted(kinds.items()):
        machine = Machine.from_dict(json.loads(text))
        choices.append({"machine": json.loads(text), "workers": workers, "live": choices_by_input(machine, live=True),
                        "recorded": choices_by_input(machine, live=False)})
    return {"presets": preset_list(), "input_modes": INPUT_MODES, "auto_choices": choices}
