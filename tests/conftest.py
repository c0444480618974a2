"""Test configuration: float64 everywhere (the library itself never changes torch defaults)."""

import os

import pytest
import torch


@pytest.fixture(autouse=True)
def _float64():
    old = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    yield
    torch.set_default_dtype(old)


@pytest.fixture
def keep_environment():
    """Restore ``os.environ`` after the test: Dask's nanny writes its workers' settings
    (OMP_NUM_THREADS=1, PYTHONHASHSEED, ...) into this process's environment whenever it
    (re)starts a worker, and the tests after it must run as they would alone."""
    env = dict(os.environ)
    yield
    os.environ.clear()
    os.environ.update(env)


@pytest.fixture
def one_thread():
    """One intra-op thread for the test, restored after it: small batched solves run several
    times faster so on a shared machine (two threads wait on each other's cores). Use it with
    ``pytestmark = pytest.mark.usefixtures("one_thread")``."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)
