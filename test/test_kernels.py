"""Every CUDA kernel compiles, without a GPU: NVRTC (the nvidia-cuda-nvrtc wheel of the test
extra) builds each kernels/*.cu with the defines its stage module launches it with, for the
architecture of the GPU machine (sm_90). Skipped where that wheel is absent."""

from __future__ import annotations

import ctypes
from functools import lru_cache
from pathlib import Path

import pytest

from pothole_detector import backend
from pothole_detector.stages import (census_sgm, local_road, measure, photometric, rectify,
                                     refine, road_model, superpixels, threshold)

ARCHITECTURE = "sm_90"


@lru_cache(maxsize=1)
def _nvrtc() -> ctypes.CDLL:
    nvidia = pytest.importorskip("nvidia.cu13", reason="nvidia-cuda-nvrtc is not installed")
    libraries = sorted(Path(next(iter(nvidia.__path__))).glob("lib/libnvrtc.so*"))
    if not libraries:
        pytest.skip("the nvidia-cuda-nvrtc wheel holds no libnvrtc")
    return ctypes.CDLL(str(libraries[0]))


def _compile(source: str, defines: dict[str, int]) -> str:
    """Compile kernels/``source`` with ``defines`` as the backend builds it (its headers
    inlined, the defines in the text); the empty string where it builds, else NVRTC's log."""
    nvrtc = _nvrtc()
    program = ctypes.c_void_p()
    text = backend._built_text(source, tuple(sorted(defines.items()))).encode()
    assert nvrtc.nvrtcCreateProgram(ctypes.byref(program), text, source.encode(), 0, None,
                                    None) == 0
    options = [option.encode() for option in backend.NVRTC_OPTIONS] + [
        f"--gpu-architecture={ARCHITECTURE}".encode()]
    status = nvrtc.nvrtcCompileProgram(program, len(options),
                                       (ctypes.c_char_p * len(options))(*options))
    size = ctypes.c_size_t()
    nvrtc.nvrtcGetProgramLogSize(program, ctypes.byref(size))
    log = ctypes.create_string_buffer(size.value)
    nvrtc.nvrtcGetProgramLog(program, log)
    nvrtc.nvrtcDestroyProgram(ctypes.byref(program))
    return "" if status == 0 else log.value.decode(errors="replace")


def _matcher_builds() -> list[dict[str, int]]:
    """sgm.cu's defines for level counts of a small and a full-width band, every lane count the
    matcher may pick for them, and both winner searches."""
    builds = []
    for levels in (64, 128, 368):
        lanes = census_sgm.lanes_for(levels)
        for spread in {lanes, min(32, 2 * lanes)}:
            for pair_bytes in (False, True):
                builds.append(census_sgm.kernel_defines(levels, spread, pair_bytes))
    return builds


KERNEL_BUILDS: dict[str, list[dict[str, int]]] = {
    "road.cu": [road_model._ROAD_DEFINES],
    "slic.cu": [superpixels._SLIC_DEFINES],
    "threshold.cu": [threshold._THRESHOLD_DEFINES],
    "components.cu": [{}],
    "refine.cu": [refine._REFINE_DEFINES],
    "measure.cu": [measure._MEASURE_DEFINES],
    "transform.cu": [road_model.ROAD_DEFINES],
    "sgm.cu": _matcher_builds(),
    "rectify.cu": [rectify.REMAP_DEFINES],
    "local_road.cu": [local_road._DEFINES],
    "photometric.cu": [photometric._DEFINES],
    "texture.cu": [{}],
}


def test_every_kernel_source_is_listed():
    assert sorted(KERNEL_BUILDS) == sorted(path.name for path in backend.KERNEL_DIR.glob("*.cu"))


@pytest.mark.parametrize("source", sorted(KERNEL_BUILDS))
def test_kernel_source_compiles(source):
    for defines in KERNEL_BUILDS[source]:
        log = _compile(source, defines)
        assert log == "", f"{source} with {defines}:\n{log}"


def test_a_broken_kernel_fails_to_compile():
    log = _compile("transform.cu", {key: value for key, value in road_model.ROAD_DEFINES.items()
                                    if key != "ROAD_A0"})
    assert "ROAD_A0" in log
