"""Fixtures shared by several test modules."""
import pytest
import torch


@pytest.fixture(scope="module")
def single_torch_thread():
    """Tiny tensors on a shared 2-core machine: one torch thread for the module's own ops."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)
