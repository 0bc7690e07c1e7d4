#!/usr/bin/env bash
# Run again on every GPU a session is lent, by whoever changed the CUDA path or needs the GPU's figures (README,
# docs/physics.md): the one script a device session runs.
#
# The GPU check in one call: the block schedule against flat (benchmarks/bench_blocks.py, issue 44), the CUDA
# tests (the device against the CPU on fixed bodies, f32/f64, both semantics; a planted NaN; compute graph =
# Python launches; many batches of random size), the host floor, and the GPU benchmark (compile times, µs per
# step at batch 1/32/128/512, the epoch's simulation, the update's ms per minibatch, closed-loop control steps per
# second at N = 128 and 1,024, one paper_locomotion epoch split into env/simulation/update). Every log goes under
# OUTDIR; a summary (< 12,000 characters) goes to stdout and OUTDIR/summary.txt. Budget: under 8 minutes on one
# H100 without blocks (measured 258 s on an H200), blocks < 3.5 min more.
#
#   scripts/gpu_check.sh OUTDIR          # on a CUDA machine (Python 3.12 and torch there; taichi, hydra & co. from
#                                        # .whl/, gathered by ../shared/device/gather-wheels.sh and carried along)
#   scripts/gpu_check.sh OUTDIR --cpu    # the rehearsal on a CPU machine: every step at small sizes (< 10 min;
#                                        # --rehearse is the same)
#   scripts/gpu_check.sh OUTDIR [--cpu] STEP...   # only these steps (environment blocks update gpu cuda_tests floor
#                                                 # control_scale), e.g.
#     PYTHON=python3 scripts/gpu_check.sh $OUT/check environment blocks floor   # issue 44: < 4 min on one H100
#     PYTHON=.venv/bin/python scripts/gpu_check.sh /tmp/check --rehearse environment blocks floor   # ~1-2 min here
# control_scale (issue 59: one epoch of the population and teacher presets at 1,024 bodies, benchmarks/bench_control_scale.py)
# is not in the default list, which fills most of a 10-minute call: give it a call of its own,
#     PYTHON=python3 scripts/gpu_check.sh $OUT/scale environment control_scale             # < 5 min, estimated
#
# The carry is 64 MiB with the checkout: taichi's wheel (54 MiB) fits once its C-API library, headers and examples,
# which Python's taichi does not load, are dropped:
#   bash ../shared/device/gather-wheels.sh && zip -q -d .whl/taichi-*.whl 'taichi/_lib/c_api/*' \
#     'taichi-1.7.4.data/*' 'taichi/examples/*' 'taichi/assets/static/*'          # 34 MiB left
# PYTHON picks the interpreter (default python3; `PYTHON=.venv/bin/python` here). FREEFORM_BACKEND=quadrants measures
# the other backend (carry quadrants' wheel instead of taichi's: the two do not fit the 64 MiB carry together).
set -uo pipefail
out=${1:?usage: scripts/gpu_check.sh OUTDIR [--cpu|--rehearse] [STEP...]}
shift
mode=
if [ "${1:-}" = "--cpu" ] || [ "${1:-}" = "--rehearse" ]; then mode=--cpu; shift; fi
steps=${*:-environment blocks update gpu cuda_tests floor}
for s in $steps; do
  case $s in environment|blocks|update|gpu|cuda_tests|floor|control_scale) ;; *) echo "unknown step $s" >&2; exit 2;; esac
done
mkdir -p "$out"
out=$(cd "$out" && pwd)
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
arch=cuda
[ "$mode" = "--cpu" ] && arch=cpu
export FREEFORM_CHECK_ARCH=$arch FREEFORM_BENCH_ARCH=$arch PYTHONUNBUFFERED=1

# The carried wheels, into a private directory (no registry on the GPU machine; nothing of the system touched).
if [ -d .whl ] && ! $PY -c "import taichi, hydra, omegaconf" 2>/dev/null; then
  $PY -m pip install -q --no-index --no-deps --no-compile --target /tmp/freeform-site .whl/*.whl \
    > "$out/install.log" 2>&1 || echo "wheel install failed: see install.log" >> "$out/steps.txt"
  export PYTHONPATH=/tmp/freeform-site${PYTHONPATH:+:$PYTHONPATH}
fi
export PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH}  # freeform from this checkout

: > "$out/steps.txt"
step() {  # step NAME SECONDS COMMAND...: run it with a time limit, its output to NAME.log, its status to steps.txt
  local name=$1 limit=$2 start rc
  shift 2
  case " $steps " in *" $name "*) ;; *) return 0;; esac
  start=$(date +%s)
  timeout "$limit" "$@" > "$out/$name.log" 2>&1
  rc=$?
  echo "$name: exit $rc ($([ $rc = 124 ] && echo "timed out after ")$(( $(date +%s) - start )) s)" >> "$out/steps.txt"
}

step environment 60 bash -c "nvidia-smi 2>&1 | head -15; $PY -c 'import sys, torch, numpy; print(sys.version); \
print(\"torch\", torch.__version__, \"cuda\", torch.version.cuda, torch.cuda.is_available()); print(\"numpy\", numpy.__version__)'; \
$PY -c 'from freeform.sim import runtime; print(runtime.describe()); import freeform; print(\"freeform\", freeform.__version__)'; \
git log -1 --format='commit %H %s' 2>/dev/null | cut -c1-120"
# the new figures first: a step that runs out of time leaves the others theirs
step blocks 240 $PY -m benchmarks blocks
step update 300 $PY -m benchmarks update
step gpu 270 $PY -m benchmarks gpu
step cuda_tests 260 $PY -m pytest -q -s -m cuda tests/test_cuda.py -p no:cacheprovider -p no:warnings
step floor 60 $PY -m benchmarks floor
step control_scale 270 $PY -m benchmarks control_scale

{
  echo "=== freeform GPU check ($arch) ==="
  cat "$out/steps.txt"
  echo "--- environment"
  head -c 2500 "$out/environment.log" 2>/dev/null
  echo "--- CUDA tests (device against the CPU)"
  grep -E "vs cpu|vs eager|passed|failed|Error|error" "$out/cuda_tests.log" 2>/dev/null | head -40 | cut -c1-300
  echo "--- host floor"
  grep -vE "^\[|Warning|warn|^ *$|importlib" "$out/floor.log" 2>/dev/null | tail -12 | cut -c1-300
  echo "--- block schedule against flat"
  grep -vE "^\[|Warning|warn|^ *$|importlib|^W[0-9]" "$out/blocks.log" 2>/dev/null | tail -25 | cut -c1-300
  echo "--- the update, trunk by trunk"
  grep -vE "^\[|Warning|warn|^ *$|importlib|^W[0-9]" "$out/update.log" 2>/dev/null | tail -30 | cut -c1-300
  echo "--- GPU benchmark"
  grep -vE "^\[|Warning|warn|^ *$|importlib|^W[0-9]" "$out/gpu.log" 2>/dev/null | tail -25 | cut -c1-300
  echo "--- control at scale"
  grep -vE "^\[|Warning|warn|^ *$|importlib|^W[0-9]" "$out/control_scale.log" 2>/dev/null | tail -8 | cut -c1-300
  for log in blocks update cuda_tests floor gpu control_scale; do  # a failure's last lines
    if [ -f "$out/$log.log" ] && ! grep -q "^$log: exit 0 " "$out/steps.txt"; then
      echo "--- last lines of $log.log"
      tail -n 25 "$out/$log.log" | cut -c1-300
    fi
  done
} | head -c 11500 | tee "$out/summary.txt"
