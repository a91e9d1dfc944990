"""Shared settings of the ``bench`` tests."""

from tiny_training import tiny_checkpoint  # noqa: F401  (a checkpoint of the tiny network in the test folder)
from torch_threads import single_torch_thread  # noqa: F401  (autouse: one torch thread)
