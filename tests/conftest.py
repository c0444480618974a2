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
