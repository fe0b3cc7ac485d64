"""``python -m pothole_detector.stages``: compile every CPU kernel of the stages (Numba's) into
Numba's cache now, so that no later start waits for the compiler; set-up runs it."""

from __future__ import annotations

import time

from .host_kernels import compile_cpu_kernels

started = time.perf_counter()
compile_cpu_kernels()
print(f"CPU kernels ready in {time.perf_counter() - started:.1f} s")
