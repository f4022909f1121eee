"""Fixtures of the spectral-stepper tests: one torch thread per test (restored afterwards).

The tests use small arrays, for which intra-op threads only add contention; on a shared two-core machine extra
threads made single tests tens of times slower.
"""

from __future__ import annotations

import pytest
import torch


@pytest.fixture(autouse=True)
def _one_torch_thread():
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)
