"""Shared settings of the ``export`` tests."""

from torch_threads import single_torch_thread  # noqa: F401  (autouse: one torch thread)
