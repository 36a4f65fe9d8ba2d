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

`pip install --no-build-isolation .` (or `-e .`) into an environment that has torch also installs
the tools: `tools/` becomes the package `icomma_tools` with `conf/` inside it as package data
(`tools/_paths.py` finds either place), and the console commands icomma-localize,
icomma-benchmark, icomma-fit and icomma-bench. torch is a prerequisite that this file checks and
never installs: install_requires carries the same range as requirements.txt, which the existing
torch satisfies (checked below before pip resolves anything), so pip leaves torch alone.
"""
from __future__ import annotations

import importlib.util
import os
import re
from pathlib import Path

from setuptools import find_packages, setup

ROOT = Path(__file__).resolve().parent


def _load_build_params():
    """gaussian_renderer_pose/_build.py, loaded by path (importing the package needs torch)."""
    spec = importlib.util.spec_from_file_location(
        "_grp_build", ROOT / "gaussian_renderer_pose" / "_build.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _requirements(name: str) -> list:
    """Requirement lines of a requirements file (comments and blank lines dropped)."""
    lines = (line.split("#", 1)[0].strip() for line in (ROOT / name).read_text().splitlines())
    return [line for line in lines if line]


def _name(requirement: str) -> str:
    return re.split(r"[\s\[<>=!~;]", requirement, maxsplit=1)[0].lower()


# Lines of requirements.txt that only the test suite and CI's lint need: extras 'test', not
# install_requires.
_TEST_ONLY = {"pytest", "hypothesis", "ruff"}


def _install_requires() -> list:
    """requirements.txt less the test-only lines; the torch line is kept as a range."""
    return [r for r in _requirements("requirements.txt") if _name(r) not in _TEST_ONLY]


def _check_torch() -> None:
    """Fail early, with the fix, when torch is missing or outside requirements.txt's range.

    So pip never has to install torch: it would fetch a build (CUDA or not) that does not match
    the user's, or any torch at all into an isolated build environment.
    """
    spec = next((r for r in _requirements("requirements.txt") if _name(r) == "torch"), "torch")
    try:
        import torch
    except ImportError:
        raise SystemExit(
            "icomma needs torch installed first (it never installs torch itself): "
            "`pip install torch==2.13.0` (CPU) or your CUDA build, then "
            "`pip install --no-build-isolation .` (without --no-build-isolation pip builds in an "
            "isolated environment that has no torch)") from None
    try:
        from packaging.requirements import Requirement
    except ImportError:  # no packaging: the import check above is all we can do
        return
    if not Requirement(spec).specifier.contains(torch.__version__, prereleases=True):
        raise SystemExit(f"icomma needs {spec}; this environment has torch {torch.__version__}")


def _config_package_data() -> list:
    """conf/'s YAML files, as patterns relative to conf/ (package icomma_tools.conf)."""
    conf = ROOT / "conf"
    return sorted({(p.parent.relative_to(conf) / "*.yaml").as_posix()
                   for p in conf.rglob("*.yaml")})


def get_extensions():
    """The native extension to build: CUDA or CPU (see this file's docstring), or none."""
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
    """torch's BuildExtension for build_ext (keeps the Python ABI suffix on _C*.so)."""
    if os.environ.get("GRP_NO_EXTENSION") == "1":
        return {}
    from torch.utils.cpp_extension import BuildExtension

    return {"build_ext": BuildExtension.with_options(no_python_abi_suffix=False)}


_check_torch()

setup(
    name="icomma",
    version="0.1.0",
    description="Camera pose estimation by inverting a trained 3D Gaussian Splatting model",
    packages=find_packages(include=["gaussian_renderer_pose*", "icomma_plugin*"])
    + ["icomma_tools", "icomma_tools.conf"],
    package_dir={"icomma_tools": "tools", "icomma_tools.conf": "conf"},
    package_data={"icomma_tools.conf": _config_package_data()},
    entry_points={"console_scripts": [
        "icomma-localize = icomma_tools.localize:main",
        "icomma-benchmark = icomma_tools.benchmark:main",
        "icomma-fit = icomma_tools.fit_scene:main",
        "icomma-bench = icomma_tools.bench_rasterizer:main",
        "icomma-bench-localize = icomma_tools.bench_localize:main",
        "icomma-audit = icomma_tools.audit:main",
    ]},
    install_requires=_install_requires(),
    extras_require={"test": [r for r in _requirements("requirements.txt")
                             if _name(r) in _TEST_ONLY]},
    python_requires=">=3.9",
    ext_modules=get_extensions(),
    cmdclass=get_cmdclass(),
    zip_safe=False,
)
