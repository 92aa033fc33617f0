"""Shared fixtures. Torch thread counts are set here, per module, never at import time (an
import-time ``torch.set_num_threads`` leaks into every test collected after it)."""
import pytest
import torch


@pytest.fixture(scope="module")
def torch_two_threads():
    """Run a module's tests with 2 torch threads (the build machine's core count), then
    restore the previous setting."""
    old = torch.get_num_threads()
    torch.set_num_threads(2)
    yield
    torch.set_num_threads(old)
