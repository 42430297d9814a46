"""What the gateway, the workers and the client SDK agree on, with no torch and nothing from `worker`, `service`
or `client` :

- `keys`: the Redis key layout
- `codec`: the msgpack codec (numpy arrays as raw bytes; never pickle)
- `image_header`: an encoded image's size from its header
"""
