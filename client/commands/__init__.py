"""Sub-commands of the `flashmono` CLI, one module each (see client.cli)."""
