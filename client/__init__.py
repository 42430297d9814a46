"""Flash-Mono client: Python SDK and the `flashmono` command line."""
