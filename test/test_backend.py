from __future__ import annotations

import numpy as np
import pytest

from pothole_detector.backend import CPU, get_backend, gpu_available, to_host
from pothole_detector.errors import BackendError


def test_cpu_backend_is_numpy():
    backend = get_backend("cpu")
    assert backend is CPU and backend.xp is np and not backend.is_gpu
    array = np.arange(4)
    assert backend.upload(array) is not None and to_host(array) is array


def test_unknown_backend_is_refused():
    with pytest.raises(BackendError, match="unknown backend"):
        get_backend("tpu")


def test_auto_falls_back_to_cpu_without_a_gpu():
    backend = get_backend("auto")
    assert backend.is_gpu == gpu_available()


@pytest.mark.skipif(gpu_available(), reason="a GPU is present")
def test_gpu_request_without_a_gpu_says_what_to_do():
    with pytest.raises(BackendError, match="--backend cpu"):
        get_backend("gpu")
