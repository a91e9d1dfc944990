"""The HTTP API: FastAPI app, request/response schemas, model registry, routes (torch-free)."""
