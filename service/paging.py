"""Listings newest first, a page at a time, over an index of records (sessions, maps): a lexicographic Redis zset of
members "<created_us>:<id>" (score 0), each naming the hash of one record."""

from __future__ import annotations

from collections.abc import Callable
from datetime import UTC, datetime

import redis.asyncio as aioredis


async def index_page(client: aioredis.Redis, index: str, record_key: Callable[[str], str],
                     keep: Callable[[dict[str, str]], bool], limit: int,
                     cursor: str | None) -> tuple[list[dict[str, str]], str | None]:
    """The records (decoded hashes) of up to `limit` members of `index` after `cursor`, newest first, that `keep`
    accepts (records since deleted are left out). `cursor` is the member of the last record of the previous page;
    the next cursor is None exactly when no further record matches."""
    matches: list[tuple[str, dict[str, str]]] = []
    upper = f"({cursor}" if cursor else "+"
    batch = max(limit * 2, 50)
    while len(matches) <= limit:
        members = await client.zrevrangebylex(index, upper, "-", start=0, num=batch)
        if not members:
            break
        pipe = client.pipeline(transaction=False)
        for member in members:
            pipe.hgetall(record_key(member.decode().split(":", 1)[-1]))
        for member, raw in zip(members, await pipe.execute()):
            upper = f"({member.decode()}"
            record = {k.decode(): v.decode() for k, v in raw.items()}
            if record and keep(record):
                matches.append((member.decode(), record))
                if len(matches) > limit:
                    break
        if len(members) < batch:
            break
    page = matches[:limit]
    return [record for _, record in page], page[-1][0] if len(matches) > limit else None


def index_member(item_id: str) -> str:
    """The index member of a record created now."""
    return f"{datetime.now(UTC).timestamp() * 1e6:020.0f}:{item_id}"

