"""A run with several workers runs BLAS and torch single-threaded and gives the settings back
afterwards (two workers' concurrent OpenBLAS matmuls deadlocked an `embody run`; a second torch
thread per worker only waited)."""

import threading

import numpy as np
import pytest
import torch
from threadpoolctl import threadpool_info, threadpool_limits

from embody.device import torch_threads
from embody.flows.threads import worker_threads


def _blas_threads() -> list[int]:
    return [i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"]


def test_several_workers_get_one_blas_thread_and_the_setting_returns():
    with threadpool_limits(limits=2, user_api="blas"):
        assert _blas_threads() and all(n == 2 for n in _blas_threads())
        with worker_threads(2):
            assert all(n == 1 for n in _blas_threads())
            # two threads' float32 matmuls at once (the metrics step's skinning shape) finish
            a = np.random.default_rng(0).random((3000, 60), dtype=np.float32)
            b = np.random.default_rng(1).random((64, 60, 12), dtype=np.float32)
            out: list[np.ndarray] = []
            threads = [threading.Thread(target=lambda: out.append(a @ b)) for _ in range(2)]
            for t in threads:
                t.start()
            for t in threads:
                t.join(timeout=60)
            assert len(out) == 2 and np.array_equal(out[0], out[1])
        assert all(n == 2 for n in _blas_threads())
        with worker_threads(1):
            assert all(n == 2 for n in _blas_threads())


@pytest.fixture
def two_torch_threads():
    """Torch at two intra-op threads for the test, then as before."""
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    yield
    torch.set_num_threads(before)


def test_several_workers_get_one_torch_thread_and_the_setting_returns(two_torch_threads):
    with worker_threads(2):
        assert torch.get_num_threads() == 1
    assert torch.get_num_threads() == 2
    with worker_threads(1):
        assert torch.get_num_threads() == 2
    with pytest.raises(RuntimeError), worker_threads(3):
        raise RuntimeError("a failing run")
    assert torch.get_num_threads() == 2


def test_torch_threads_sets_the_count_and_gives_the_setting_back(two_torch_threads):
    """`torch_threads` (the metrics step's and the collision optimiser's one intra-op thread)
    sets the count inside the block; the setting before it comes back afterwards, also when the
    step fails."""
    with torch_threads(1):
        assert torch.get_num_threads() == 1
    assert torch.get_num_threads() == 2
    with pytest.raises(RuntimeError), torch_threads(1):
        raise RuntimeError("a failing step")
    assert torch.get_num_threads() == 2
