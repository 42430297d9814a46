"""The worker process: Redis streams consumer, session leases, snapshots to Redis, render/export requests.

Importing this package is cheap (no torch); the engine is loaded only by `worker.runtime.engine`.
"""
