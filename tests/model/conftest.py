"""Shared settings of the ``model`` tests."""

from __future__ import annotations

import pytest
import torch


@pytest.fixture(autouse=True, scope="session")
def _single_torch_thread():
    """One intra-op thread: the tiny tensors here gain nothing from more, and on a machine whose cores
    are busy (a training run beside the tests) OpenMP oversubscription makes each op ~50x slower."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)
