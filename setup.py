"""Build/install icomma (pytorch3d-style).

`python setup.py build_ext --inplace` builds gaussian_renderer_pose/_C*.so in place:
- a CppExtension (CPU kernels, OpenMP) always;
- a CUDAExtension instead, when torch has CUDA (`torch.version.cuda`) AND
  `torch.utils.cpp_extension.CUDA_HOME` is set AND `_build.cuda_sources` is non-empty. The presence
  of nvcc on PATH is never used as a signal.
Environment: GRP_NO_EXTENSION=1 -> pure-Python install (reference backend only);
GRP_NO_CUDA=1 -> CPU extension only even where torch has CUDA (e.g. when the local nvcc does not
match torch's CUDA version); GRP_PORTABLE=1 -> no -march=native. torch is not a build requirement
(no build isolation: `pip install --no-build-isolation -e .`).
"""
from __future__ import annotations

import importlib.util
import os
from pathlib import Path

from setuptools import find_packages, setup

ROOT = Path(__file__).resolve().parent


def _load_build_params():
    spec = importlib.util.spec_from_file_location("_grp_build", ROOT / "gaussian_renderer_pose" / "_build.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def get_extensions():
    if os.environ.get("GRP_NO_EXTENSION") == "1":
        return []
    import torch
    from torch.utils.cpp_extension import CUDA_HOME, CppExtension, CUDAExtension

    params = _load_build_params()
    with_cuda = (
        torch.version.cuda is not None
        and CUDA_HOME is not None
        and len(params.cuda_sources) > 0
        and os.environ.get("GRP_NO_CUDA") != "1"
    )
    sources = list(params.cpu_sources) + (list(params.cuda_sources) if with_cuda else [])
    kwargs = dict(
        sources=sources,
        include_dirs=[str(ROOT / d) for d in params.include_dirs],
        extra_link_args=list(params.extra_link_args),
    )
    if with_cuda:
        return [
            CUDAExtension(
                "gaussian_renderer_pose._C",
                define_macros=[("GRP_WITH_CUDA", None)],
                extra_compile_args={k: list(v) for k, v in params.extra_compile_args.items()},
                **kwargs,
            )
        ]
    return [
        CppExtension(
            "gaussian_renderer_pose._C",
            extra_compile_args={"cxx": list(params.extra_compile_args["cxx"])},
            **kwargs,
        )
    ]


def get_cmdclass():
    if os.environ.get("GRP_NO_EXTENSION") == "1":
        return {}
    from torch.utils.cpp_extension import BuildExtension

    return {"build_ext": BuildExtension.with_options(no_python_abi_suffix=False)}


setup(
    name="icomma",
    version="0.1.0",
    description="Camera pose estimation by inverting a trained 3D Gaussian Splatting model",
    packages=find_packages(include=["gaussian_renderer_pose*", "icomma_plugin*"]),
    python_requires=">=3.9",
    ext_modules=get_extensions(),
    cmdclass=get_cmdclass(),
    zip_safe=False,
)
