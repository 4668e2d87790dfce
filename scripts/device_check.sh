#!/usr/bin/env bash
# The one prepared run on a lent GPU machine (README, Speed; docs/device_runs.md): the machine, CPU against GPU
# on the same inputs, the device-parametrized tests on CUDA, the benchmark on CUDA, a profile.
#   bash scripts/device_check.sh                       # every step; logs under $OUT (default out/device_check)
#   STEPS="tests profile" bash scripts/device_check.sh # some of them
# Steps: graphs_ab tests bench_bd bench_eager profile agreement bench_a compile (graphs_ab: the CUDA
# graphs against eager loops in one process, runs alternated; bench_eager: part b at B=4096 with
# run.cuda_graphs off, in a process of its own). Each has its own time limit (T_<STEP>
# seconds), so one that hangs costs only its share. Wheels in .whl/ (packages the machine's image
# lacks: kornia, kornia_rs, shapely) are installed first.
set -u
OUT=${OUT:-out/device_check}
STEPS=${STEPS:-graphs_ab tests bench_bd profile agreement bench_a}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1 OMP_NUM_THREADS=1
if ls .whl/*.whl >/dev/null 2>&1; then
    site="$PWD/build/device_site"                # git-ignored, inside the checkout
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target "$site" .whl/*.whl \
        && export PYTHONPATH=$site
fi
export PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH}
{ nvidia-smi --query-gpu=name,memory.total,driver_version,clocks.sm,clocks.max.sm --format=csv
  python3 -c "import torch, sys; print('python', sys.version.split()[0], 'torch', torch.__version__, torch.cuda.get_device_name(0))"
} 2>&1 | tee "$OUT/env.txt"
step() {
    local name=$1 limit=$2; shift 2
    case " $STEPS " in *" $name "*) ;; *) return 0 ;; esac
    echo "=== $name (limit $limit s, at $SECONDS s)"
    timeout "$limit" "$@" > "$OUT/$name.log" 2>&1
    echo "=== $name rc=$? (at $SECONDS s)"
    tail -n "${TAIL:-30}" "$OUT/$name.log"
}
TAIL=20 step graphs_ab "${T_GRAPHS_AB:-240}" python3 scripts/benchmark_graphs.py --device cuda --batches 4096,512 --hard 64 --repeats 3 --modes "${GRAPHS_MODES:-off,on,anneal,quarter,trials1}"
TAIL=15 step tests "${T_TESTS:-120}" python3 -m pytest -q -p no:cacheprovider -n 8 -k "cuda or graphs" tests
step bench_bd "${T_BENCH_BD:-150}" python3 scripts/benchmark.py --device cuda --parts bd --batches 256,1024,4096 --subset 4 --repeats "${REPEATS:-3}"
step bench_eager "${T_BENCH_EAGER:-120}" python3 scripts/benchmark.py --device cuda --parts b --batches 4096 --subset 1 --repeats "${REPEATS:-3}" --set cuda_graphs=false
TAIL=45 step profile "${T_PROFILE:-90}" python3 scripts/profile_device.py --device cuda --B 512 --top 12
step agreement "${T_AGREEMENT:-100}" python3 scripts/device_agreement.py --device cuda --threads 16 --batch 256 --hard 64 --masks "${MASKS:-200}"
step bench_a "${T_BENCH_A:-60}" python3 scripts/benchmark.py --device cuda --parts a --sizes 1000,100000 --repeats "${REPEATS:-3}"
step compile "${T_COMPILE:-150}" python3 scripts/benchmark.py --device cuda --parts b --batches 4096 --subset 1 --repeats 3 --set compile=true
echo "=== warnings about graphs:"; grep -h "CUDA graph" "$OUT"/*.log | sort | uniq -c | head -5
