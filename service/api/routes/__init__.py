"""Thin route modules: parse the request, call the runner, shape the response."""
