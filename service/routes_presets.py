"""GET /v1/presets: the engine presets a session can name, what each is for and which input suits it."""

from __future__ import annotations

from fastapi import APIRouter, Depends

from service.auth import Principal, caller
from service.presets import INPUT_MODES, preset_list
from service.schemas import ErrorBody, PresetList

router = APIRouter(prefix="/v1/presets", tags=["sessions"], responses={401: {"model": ErrorBody}})


@router.get("", response_model=PresetList)
async def list_presets(principal: Principal = Depends(caller)) -> dict:
    """The presets for `POST /v1/sessions` (any valid key), and how the input mode follows from a frame's fields."""
    return {"presets": preset_list(), "input_modes": INPUT_MODES}
