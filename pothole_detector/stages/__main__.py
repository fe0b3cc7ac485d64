"""``python -m pothole_detector.stages``: compile the CPU kernels (the census matcher's,
rectification's and SLIC's, Numba) into Numba's cache now, so that no later start waits for
the compiler; set-up runs it."""

from __future__ import annotations

import time

from .census_sgm import compile_cpu_kernels
from .rectify import compile_cpu_kernel
from .superpixels import compile_cpu_kernels as compile_slic_kernels

started = time.perf_counter()
compile_cpu_kernels()
compile_cpu_kernel()
compile_slic_kernels()
print(f"CPU kernels ready in {time.perf_counter() - started:.1f} s")
