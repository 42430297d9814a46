"""Mapping in a process of its own beside tracking (issue 42): the session keeps tracking and loop closing in its
process; the map, multi-view depth and refinement run in a mapping process forked for the session.

- `proxy.MappingProcess`: the session's side, with the MappingStage interface (worker.pipeline.mapping_stage);
- `child`: the process's side, a MappingStage served over the channel;
- `channel`: msgpack messages over a pipe (nothing pickled);
- `launcher`: processes forked from a server that has imported the engine once.
"""

from worker.pipeline.mapping_process.proxy import MappingProcess

__all__ = ["MappingProcess"]
