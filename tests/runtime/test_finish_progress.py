"""While a session finishes, `finishing` messages with the elapsed time reach its outbox (real redis-server)."""

from __future__ import annotations

import json
import time

import pytest
import redis
from redis.backoff import NoBackoff
from redis.retry import Retry

from protocol import keys
from service.redis_embedded import EmbeddedRedis
from worker.runtime.progress import FinishProgress


@pytest.fixture(scope="module")
def client():
    with EmbeddedRedis() as server:
        connection = redis.Redis.from_url(server.url)
        yield connection
        connection.close()


def _outbox(client, session_id: str) -> list[dict]:
    return [json.loads(fields[b"msg"]) for _, fields in client.xrange(keys.outbox(session_id))]


def test_progress_is_posted_at_the_start_and_while_finishing(client):
    with FinishProgress(client, "s-slow", every_s=0.1):
        time.sleep(0.45)
    messages = _outbox(client, "s-slow")
    assert all(m["type"] == "finishing" for m in messages)
    elapsed = [m["elapsed_s"] for m in messages]
    assert elapsed[0] == 0.0 and len(elapsed) >= 3 and elapsed == sorted(elapsed)
    time.sleep(0.3)
    assert len(_outbox(client, "s-slow")) == len(messages)  # nothing after the finish ended


def test_a_quick_finish_posts_one_message(client):
    with FinishProgress(client, "s-quick", every_s=5.0):
        pass
    assert _outbox(client, "s-quick") == [{"type": "finishing", "elapsed_s": 0.0}]


def test_a_redis_failure_does_not_break_the_finish():
    dead = redis.Redis(host="127.0.0.1", port=1, socket_connect_timeout=0.2, retry=Retry(NoBackoff(), 0))
    with FinishProgress(dead, "s-dead", every_s=0.05):
        time.sleep(0.1)
    with pytest.raises(ValueError):
        FinishProgress(dead, "x", every_s=0)
