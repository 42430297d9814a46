"""The viewer tests' browser: headless Chromium, installed once per run if needed."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))
from cdp import ensure_chromium  # noqa: E402


@pytest.fixture(scope="session")
def chromium() -> str:
    """Chromium, installed if needed; FLASHMONO_REQUIRE_CHROMIUM=1 turns a missing browser into a failure."""
    try:
        return ensure_chromium()
    except RuntimeError as err:
        if os.environ.get("FLASHMONO_REQUIRE_CHROMIUM") == "1":
            pytest.fail(f"headless Chromium is required here and unavailable: {err}")
        pytest.skip(f"headless Chromium unavailable: {err}")
