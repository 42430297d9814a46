"""One-shot move of a single Redis instance's data from the key layout before hash tags to today's
(`protocol.keys`): `python -m worker.runtime.migrate --redis-url redis://host:6379/0`.

Run it once with the gateways and workers stopped (`flashmono serve` runs it itself on its embedded Redis at
start). Every key of each session is renamed to its hash-tagged name (RENAME keeps the value, its TTL and a
stream's consumer groups); each session still live gets a new job in its partition of the jobs queue (the old
`fm:jobs` stream and its pending entries are dropped), and the old `fm:requests` stream is dropped (a request
waiting there had long timed out). A second run finds nothing to move. To go from a single instance to a cluster,
migrate on the single instance first, then copy its keys into the cluster (e.g. `redis-cli --cluster import`).
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass

import redis

from protocol import keys

# Sessions in these states need a worker (a job); abandoned ones get a job again when their stream is re-opened.
_NEED_JOB = keys.LIVE_STATUSES


@dataclass
class MigrationReport:
    sessions: int = 0  # sessions whose keys were moved
    keys_moved: int = 0
    jobs_requeued: int = 0
    conflicts: int = 0  # old keys left in place because the new name already existed


def legacy_session_ids(client: redis.Redis) -> list[str]:
    """Ids of the sessions stored under the old layout (their record `fm:session:<id>` still exists)."""
    prefix = keys.LEGACY_SESSION_PREFIX
    return sorted(k.decode()[len(prefix):] for k in client.scan_iter(match=f"{prefix}*", count=1000))


def migrate(client: redis.Redis) -> MigrationReport:
    """Move every legacy session's keys and requeue the live ones; safe to run again."""
    report = MigrationReport()
    for session_id in legacy_session_ids(client):
        for old, new in keys.legacy_session_keys(session_id).items():
            if not client.exists(old):
                continue
            if client.renamenx(old, new):
                report.keys_moved += 1
            else:
                report.conflicts += 1
        report.sessions += 1
        status = client.hget(keys.session(session_id), "status")
        if status is not None and status.decode() in _NEED_JOB:
            client.xadd(keys.jobs(session_id), {"session_id": session_id})
            report.jobs_requeued += 1
    client.delete(keys.LEGACY_JOBS, keys.LEGACY_REQUESTS)
    return report


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m worker.runtime.migrate", description=__doc__.split("\n\n")[0])
    parser.add_argument("--redis-url", required=True, help="the single instance to migrate (redis://, unix://)")
    args = parser.parse_args(argv)
    if args.redis_url.split(":", 1)[0].endswith("+cluster"):
        print("error: migrate the single instance the data is on (then copy it into the cluster)", file=sys.stderr)
        return 2
    client = redis.Redis.from_url(args.redis_url)
    try:
        report = migrate(client)
    except redis.ConnectionError as err:
        print(f"error: cannot reach Redis at {args.redis_url}: {err}", file=sys.stderr)
        return 1
    print(f"moved {report.keys_moved} keys of {report.sessions} sessions; {report.jobs_requeued} live sessions "
          f"requeued; {report.conflicts} keys left in place (the new name existed)")
    return 0 if report.conflicts == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
