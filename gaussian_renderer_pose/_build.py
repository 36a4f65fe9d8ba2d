"""The one list of native sources and compiler flags, read by setup.py (and a future JIT path).

Paths are relative to the repository root. Plain Python with no imports of torch, so that it can be
loaded with importlib before anything is built.
"""
from __future__ import annotations

import os

_CSRC = "gaussian_renderer_pose/csrc"

# Always compiled (CppExtension): bindings + the CPU kernels. Two translation units.
cpu_sources = [
    f"{_CSRC}/ext.cpp",
    f"{_CSRC}/cpu/rasterize_cpu.cpp",
]

# Compiled only when torch has CUDA and CUDA_HOME is set (CUDAExtension, -DGRP_WITH_CUDA):
# the pure-CUDA kernels (nvcc) and their torch-facing wrapper (host compiler).
# tests/gaussian_renderer_pose/test_cuda_compile.py compiles them with nvcc on machines without a
# GPU.
cuda_sources: list[str] = [
    f"{_CSRC}/cuda/kernels.cu",
    f"{_CSRC}/cuda/rasterize_cuda.cpp",
]

include_dirs = [_CSRC]


def _cxx_flags() -> list[str]:
    flags = ["-O3", "-fopenmp"]
    # -march=native: the extension is always built on the machine that runs it.
    # GRP_PORTABLE=1 builds a binary that runs on any x86-64 / aarch64 machine.
    if os.environ.get("GRP_PORTABLE") != "1":
        flags.append("-march=native")
    return flags


extra_compile_args = {
    "cxx": _cxx_flags(),
    "nvcc": ["-O3", "--expt-relaxed-constexpr"],
}

extra_link_args = ["-fopenmp"]
