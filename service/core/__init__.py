"""Settings and logging shared by the HTTP service."""
