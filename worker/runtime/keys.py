"""Moved to `protocol.keys` (the Redis key layout is shared by the gateway and the workers); kept for old imports."""

from protocol.keys import *  # noqa: F401,F403
from protocol.keys import _tagged  # noqa: F401
