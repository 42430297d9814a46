"""What the gateway, the workers and the client SDK agree on, with no torch and nothing from `worker`, `service`
or `client` (pyproject.toml's import contracts check it):

- `keys`: the Redis key layout
- `codec`: the msgpack codec (numpy arrays as raw bytes; never pickle)
- `image_header`: an encoded image's size from its header
- `limits`: sizes the gateway enforces and the engine honours, each defined once
- `presets`: the preset names a session may ask for
- `poses`: the wire's camera-to-world similarities (scale, quaternions)
- `map_package`: the map package file format (`flashmono.map/1`): a saved map, its keyframes and surfels
- `splats`: Gaussian splat files (the engine's PLY as numpy records, SPZ, .splat): the map formats served
- `messages`: typed WebSocket messages with their error and close codes; `schema`: their JSON schemas
"""
