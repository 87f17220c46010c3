import pytest
import torch


@pytest.fixture(autouse=True)
def one_thread():
    """Tiny networks run far faster on one thread than on threads competing for shared cores."""
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)
