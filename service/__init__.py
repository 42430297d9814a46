"""Flash-Mono gateway: FastAPI routes, auth, schemas and the Redis session registry."""
