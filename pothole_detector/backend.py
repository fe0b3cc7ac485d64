"""The one switch between NumPy (CPU) and CuPy (GPU).

This is the only module that imports CuPy. Stages receive an array module ``xp`` and return
arrays of the same kind as their inputs.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from types import ModuleType
from typing import Any

import numpy as np
import scipy.ndimage

from .errors import BackendError

try:
    import cupy as _cupy
    import cupyx.scipy.ndimage as _cupy_ndimage
except Exception:  # noqa: BLE001 - any import failure means "no GPU backend"
    _cupy = None
    _cupy_ndimage = None

_log = logging.getLogger(__name__)
BACKEND_CHOICES = ("auto", "cpu", "gpu")


@dataclass(frozen=True)
class Backend:
    """An array backend: ``xp`` is numpy or cupy, ``ndimage`` the matching scipy.ndimage."""

    name: str
    xp: ModuleType
    ndimage: ModuleType

    @property
    def is_gpu(self) -> bool:
        return self.name == "gpu"

    def upload(self, array: np.ndarray) -> Any:
        """Copy a host array to the backend (no copy on the CPU backend)."""
        return self.xp.asarray(array)

    def to_host(self, array: Any) -> np.ndarray:
        """Copy a backend array to a NumPy array (no copy on the CPU backend)."""
        return to_host(array)

    def synchronize(self) -> None:
        """Wait for queued device work (no-op on the CPU backend), e.g. before reading a clock."""
        if self.is_gpu:
            self.xp.cuda.get_current_stream().synchronize()


CPU = Backend("cpu", np, scipy.ndimage)


def gpu_available() -> bool:
    """True when CuPy imports and sees at least one CUDA device."""
    if _cupy is None:
        return False
    try:
        return _cupy.cuda.runtime.getDeviceCount() > 0
    except Exception:  # noqa: BLE001 - driver missing or broken: no GPU
        return False


def get_backend(name: str = "auto") -> Backend:
    """Return the backend called ``name`` (auto, cpu or gpu).

    ``auto`` picks the GPU when CuPy sees a device, else the CPU with one log line.
    """
    if name not in BACKEND_CHOICES:
        raise BackendError(f"unknown backend {name!r}: use one of {', '.join(BACKEND_CHOICES)}")
    if name == "cpu":
        return CPU
    if gpu_available():
        return Backend("gpu", _cupy, _cupy_ndimage)
    if name == "gpu":
        raise BackendError(
            "backend 'gpu' needs CuPy and a CUDA device (pip install cupy-cuda12x or "
            "cupy-cuda13x); use --backend cpu or auto on this machine"
        )
    _log.info("no CUDA device visible to CuPy: using the CPU backend")
    return CPU


def array_module(array: Any) -> ModuleType:
    """numpy or cupy, whichever owns ``array``."""
    if _cupy is not None and isinstance(array, _cupy.ndarray):
        return _cupy
    return np


def to_host(array: Any) -> np.ndarray:
    """NumPy view or copy of a NumPy or CuPy array."""
    if _cupy is not None and isinstance(array, _cupy.ndarray):
        return _cupy.asnumpy(array)
    return np.asarray(array)
