#!/usr/bin/env bash
# The CUDA backend's checks and timings on a machine with an NVIDIA GPU, in one call.
#
#   OUT=gpu_out bash tools/gpu_check.sh [STEP ...]     # default: every step, in this order
#
# Steps (each under its own time limit and the whole run's deadline, GPU_CHECK_DEADLINE seconds
# from the start, default 540; a failed step does not stop the next):
#   env     the GPU, torch, nvcc
#   build   the CUDA extension in place (TORCH_CUDA_ARCH_LIST, default 9.0; skipped when a _C*.so
#           that has WITH_CUDA is already there, e.g. carried from an earlier run); a copy without
#           debug sections goes to $OUT
#   test    tests/gaussian_renderer_pose/test_cuda.py (CUDA vs native CPU vs float64 reference,
#           every gradient, determinism) and the localizer's end-to-end CUDA tests
#   demo    tools/localize.py on the built-in demo scene with renderer=cuda, then renderer=cpu
#   speed   tools/bench_localize.py --scenes demo --methods robust (10 starts, then one under
#           torch.profiler: $OUT/profile_<backend>.txt), this backend, then cpu
#   raster  tools/bench_rasterizer.py --backends cuda,cpu (300k and 1M Gaussians, 200 and 800 px)
#   fit     tools/fit_scene.py --backend cuda on the captures of GPU_CHECK_FITS ("capture:r:its",
#           its 0 = the recipe's count; default fox:4:0) under $GPU_CHECK_DATA, each then --evaluate
#   longfit the fit step again on GPU_CHECK_LONGFITS (default goldcape:4:20000: a longer schedule)
#   bench   tools/benchmark.py real_capture (1 start a photo, seed 12) on the fit GPU_CHECK_BENCH
#           (default fox_r4_i0), renderer=cuda
# Python packages the machine lacks travel as wheels in .whl/ (installed first when present).
# Everything goes to $OUT/log.txt; $OUT/summary.txt has one line per step (rc, seconds).
set -u
OUT=${OUT:-gpu_out}
mkdir -p "$OUT"
PY=${PYTHON:-python3}
DEADLINE=$(( $(date +%s) + ${GPU_CHECK_DEADLINE:-540} ))
DATA=${GPU_CHECK_DATA:-.gpu/data}
WORK=${GPU_CHECK_WORK:-/tmp/gpu_check}
THREADS=${GPU_CHECK_THREADS:-$(nproc)}
BACKEND=${GPU_CHECK_BACKEND:-cuda}  # cpu: a dry run of the fit and bench steps on a machine without a GPU
export PYTHONUNBUFFERED=1 MAX_JOBS=${MAX_JOBS:-16} TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-9.0}
export ICOMMA_CACHE_DIR=$WORK/cache HYDRA_FULL_ERROR=1
mkdir -p "$WORK"
LOG=$OUT/log.txt

run_step() {  # name limit_s function
  local name=$1 limit=$2
  shift 2
  local left=$(( DEADLINE - $(date +%s) ))
  if (( left < 10 )); then
    echo "$name skipped (deadline)" | tee -a "$OUT/summary.txt"
    return 0
  fi
  (( limit > left )) && limit=$left
  if [[ $name != env && $name != build && $BACKEND == cuda ]] && ! has_cuda_build; then
    echo "$name skipped (no CUDA build)" | tee -a "$OUT/summary.txt"
    return 0
  fi
  echo "===== $name (limit ${limit} s): $*" >>"$LOG"
  local t0
  t0=$(date +%s)
  timeout "$limit" bash -c "$1" >>"$LOG" 2>&1
  local rc=$?
  echo "$name rc=$rc $(( $(date +%s) - t0 )) s" | tee -a "$OUT/summary.txt"
}

has_cuda_build() {
  $PY -c "import gaussian_renderer_pose._C as c, sys; sys.exit(0 if getattr(c, 'WITH_CUDA', False) else 1)" 2>/dev/null
}

step_env() {
  nvidia-smi --query-gpu=name,memory.total,driver_version,clocks.sm --format=csv
  $PY -c "import torch; print('torch', torch.__version__, 'cuda', torch.version.cuda, torch.cuda.get_device_name(0))"
  nvcc --version | tail -n 2
  nproc
}

step_build() {
  if has_cuda_build; then echo "a CUDA build is already here"; else
    $PY setup.py build_ext --inplace || return 1
  fi
  $PY -c "from gaussian_renderer_pose import available_backends; print('backends', available_backends())"
  # without its debug sections the build fits the 16 MB a returned file may have; carried back in
  # (gaussian_renderer_pose/_C*.so) it spares the next call's build
  local so
  for so in gaussian_renderer_pose/_C*.so; do
    strip --strip-debug -o "$OUT/$(basename "$so")" "$so" 2>/dev/null || cp "$so" "$OUT"/
  done
}

step_test() {
  $PY -m pytest -q -p no:cacheprovider -rs tests/gaussian_renderer_pose/test_cuda.py \
    tests/icomma_plugin/test_localizer_cuda.py
}

step_demo() {
  for r in cuda cpu; do
    local t0=$SECONDS
    $PY tools/localize.py renderer=$r threads="$THREADS" output.dir="$WORK/demo_$r" \
      output.progress=false output.gif=false || return 1
    echo "demo renderer=$r: $(( SECONDS - t0 )) s wall (process start included)"
  done
  $PY - "$WORK" <<'EOF'
import json, sys
from pathlib import Path
rows = {r: json.loads((Path(sys.argv[1]) / f"demo_{r}" / "result.json").read_text()) for r in ("cuda", "cpu")}
for r, res in rows.items():
    keys = {k: res.get(k) for k in ("rot_err_deg", "trans_err", "seconds", "iterations", "stage_seconds")}
    v = res.get("verdict")
    keys["verdict"] = v.get("status") if isinstance(v, dict) else (v or res.get("status"))
    print("demo", r, keys)
EOF
}

step_speed() {  # seconds a pose of the default method on the demo scene: this backend, then cpu
  local b
  for b in $(echo "$BACKEND cpu" | tr ' ' '\n' | awk '!seen[$0]++'); do
    $PY tools/bench_localize.py --scenes demo --methods robust --backend "$b" \
      --threads "$THREADS" --starts ${GPU_CHECK_STARTS:-10} --out "$WORK/bench_localize_$b" \
      --profile | grep -A 12 "^| scene"
    cp "$WORK/bench_localize_$b/profile_demo_robust.txt" "$OUT/profile_$b.txt"
  done
}

step_raster() {
  $PY tools/bench_rasterizer.py --backends cuda,cpu --sizes 300000,1000000 --resolutions 200,800 \
    --threads "$THREADS" --repeats 5 --json "$OUT/raster.json"
}

step_fit() {  # GPU_CHECK_FITS: "capture:resolution:iterations ..." (iterations 0: the recipe's)
  local spec capture r its name extra
  for spec in ${GPU_CHECK_FITS:-fox:4:0}; do
    IFS=: read -r capture r its <<<"$spec"
    name=${capture}_r${r}_i${its}
    extra=""
    (( its > 0 )) && extra="--iterations $its"
    local t0=$SECONDS
    $PY tools/fit_scene.py -s "$DATA/$capture" -m "$WORK/fit_$name" -r "$r" $extra --backend "$BACKEND" \
      --device "$BACKEND" --threads "$THREADS" --no-progress --log-every 2000 --overwrite || return 1
    echo "fit $name: $(( SECONDS - t0 )) s wall"
    $PY tools/fit_scene.py --evaluate -m "$WORK/fit_$name" -s "$DATA/$capture" -r "$r" \
      --backend "$BACKEND" --device "$BACKEND" --grid "$OUT/grid_$name.png" | tail -n 12
  done
}

step_bench() {  # GPU_CHECK_BENCH: the fit (name as in step_fit) whose held-out photos are localized
  local name=${GPU_CHECK_BENCH:-fox_r4_i0}
  $PY tools/benchmark.py scene.model_path="$WORK/fit_$name" scene.query.dataset="$DATA/${name%%_r*}" \
    scene.translation_unit=scene_radius benchmark_protocol=real_capture \
    "benchmark_protocol.methods=[robust]" benchmark_protocol.poses_per_query=1 seed=12 \
    renderer="$BACKEND" threads="$THREADS" hydra.run.dir="$WORK/bench" ${GPU_CHECK_BENCH_ARGS:-} || return 1
  cp "$WORK/bench/results.json" "$OUT/bench_results.json" 2>/dev/null
  return 0
}

export OUT PY DATA WORK THREADS LOG BACKEND
export -f has_cuda_build step_env step_build step_test step_demo step_speed step_raster step_fit step_bench

if [ -d .whl ] && ls .whl/*.whl >/dev/null 2>&1; then
  $PY -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
    --target /tmp/site .whl/*.whl >>"$LOG" 2>&1 && export PYTHONPATH=/tmp/site${PYTHONPATH:+:$PYTHONPATH}
fi

STEPS=${*:-env build test demo speed raster fit bench longfit}
for s in $STEPS; do
  case $s in
    env) run_step env 60 step_env ;;
    build) run_step build 300 step_build ;;
    test) run_step test 150 step_test ;;
    demo) run_step demo 120 step_demo ;;
    speed) run_step speed 120 step_speed ;;
    raster) run_step raster 150 step_raster ;;
    fit) run_step fit 360 step_fit ;;
    bench) run_step bench 150 step_bench ;;
    longfit) export GPU_CHECK_FITS=${GPU_CHECK_LONGFITS:-goldcape:4:20000}
             run_step longfit 300 step_fit ;;
    *) echo "unknown step $s" | tee -a "$OUT/summary.txt" ;;
  esac
done
echo "----- summary"
cat "$OUT/summary.txt"
