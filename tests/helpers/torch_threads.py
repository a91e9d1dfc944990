"""A session fixture that keeps torch at one intra-op thread; conftests re-export it.

Import as ``from torch_threads import single_torch_thread`` (``tests/helpers`` is on ``sys.path``).
"""

from __future__ import annotations

import pytest


@pytest.fixture(autouse=True, scope="session")
def single_torch_thread():
    """One intra-op thread: the tiny tensors here gain nothing from more, and on a machine whose cores
    are busy (a training run beside the tests) OpenMP oversubscription makes each op ~50x slower."""
    try:
        import torch
    except ImportError:  # a runtime-only environment: nothing to pin
        yield
        return
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)
