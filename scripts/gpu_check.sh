#!/usr/bin/env bash
# The GPU path's checks in one call (issue 30): on a bare CUDA machine, from the repository root,
# install the wheels carried in .whl/ (scripts/gpu_wheels.sh: what the image lacks), JIT-build
# gsplat's CUDA extension, then run, each under its own share of the time:
#   pytest -m cuda (the GPU path's check first); a simulated recording's bytes against an AMD host's digests;
#   CPU training's thread scaling 1..16 (bench train --scaling, 128 then 512 px), the OpenMP wait
#   policy's effect at 16 threads, the CPU kernels' scaling (bench raster --scaling);
#   bench raster, bench cast (rays/s by chunk size) and bench train at 2400 px / 1M Gaussians (with
#   and without motion sampling); two simulated frames at the paper's resolution (s/frame);
#   config/paper_smoke.yaml end to end, as far as time allows (the jobs toward SMOKE_FIRST first).
# Writes OUT_DIR/summary.txt (one line per step: exit code, seconds) and OUT_DIR/logs.tar.gz (each
# step's log, the benchmarks' JSON, the smoke run's tables and logs).
#   usage: bash scripts/gpu_check.sh OUT_DIR [BUDGET_SECONDS]     (EGOBENCH_CACHE: LPIPS weights)
#   STEPS="install gsplat_build paper_smoke" bash scripts/gpu_check.sh ...   runs only the steps named
#   STEPS="paper_smoke" bash scripts/gpu_check.sh OUT 280   continues the smoke on a still-warm machine
#   STEPS="install gsplat_build ladder" bash scripts/gpu_check.sh OUT 540   the scale ladder, continued
set -u
OUT=${1:?usage: gpu_check.sh OUT_DIR [BUDGET_SECONDS]}
BUDGET=${2:-560}
LOGS=/tmp/gpu_check_logs
mkdir -p "$OUT" "$LOGS"
START=$SECONDS

left() { echo $((BUDGET - (SECONDS - START))); }

# wanted NAME: STEPS names NAME (or is unset / says all)
wanted() { [[ " ${STEPS:-all} " == *" all "* || " ${STEPS:-all} " == *" $1 "* ]]; }

# step NAME SECONDS CMD...: run CMD with at most SECONDS (and never past the budget), log to LOGS/NAME.log
step() {
  local name=$1 want=$2 budget t began rc
  shift 2
  wanted "$name" || return 0
  budget=$(left)
  t=$((want < budget ? want : budget))
  if ((t < 5)); then echo "$name: skipped (no time left)" | tee -a "$OUT/summary.txt"; return; fi
  began=$SECONDS
  timeout -k 5 "$t" "$@" >"$LOGS/$name.log" 2>&1
  rc=$?
  echo "$name: rc=$rc in $((SECONDS - began)) s (limit $t s)" | tee -a "$OUT/summary.txt"
  tail -n 4 "$LOGS/$name.log" | sed 's/^/    /' >>"$OUT/summary.txt"
}

export PYTHONUNBUFFERED=1 MAX_JOBS=16 TORCH_CUDA_ARCH_LIST=9.0 TORCH_EXTENSIONS_DIR=/tmp/torch_ext
export PYTHONPATH=$PWD:/tmp/site PATH=/tmp/site/bin:$PATH

step env 30 bash -c 'nvidia-smi; nvcc --version; lscpu | head -20; python3 -c "
import torch, numpy, numba
print(\"torch\", torch.__version__, \"cuda\", torch.version.cuda, torch.cuda.get_device_name(0))
print(\"numpy\", numpy.__version__, \"numba\", numba.__version__)"'
step install 90 python3 -m pip install --no-index --no-deps --no-compile --no-cache-dir --upgrade \
  --target /tmp/site .whl/*.whl
# which threading layer numba's parallel kernels use here (OMP_WAIT_POLICY matters only for 'omp')
step numba_layer 60 python3 -c "import numba, numpy as np
f = numba.njit(parallel=True)(lambda a: a.sum())
f(np.ones(1000)); print('numba threading layer:', numba.threading_layer())"
step gsplat_build 300 env VERBOSE=1 python3 -c "
import time; t = time.time()
from gsplat.cuda._backend import _C
print('gsplat extension:', _C, f'{time.time() - t:.1f} s')
assert _C is not None"
step pytest_cuda 100 python3 -m pytest -m cuda -v -p no:cacheprovider --continue-on-collection-errors
# the host CPU is an Intel Xeon: do a recording's bytes travel between CPU vendors? (the digests were written on an
# AMD EPYC host, results/cross_isa/recording_digests.json; exit 1 names the files that differ)
step cross_vendor_recordings 120 python3 scripts/cross_isa_check.py --out "$LOGS/cross_isa" \
  --reference-digests results/cross_isa/recording_digests.json
# the compiled CPU kernels and training on the host's 16 cores (issue 32: scaling past 2 threads)
CPU_ENV="OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=${CPU_POOL:-16} NUMBA_CACHE_DIR=/tmp/numba_cache"
for px in 128 512; do  # one record each, so that a time limit keeps the first
  step cpu_train_scaling_$px 200 bash -c "env $CPU_ENV python3 -m egobench.cli bench train --resolution $px \
    --method ours --method ours_2dgs --points 20000 --scaling 1,2,4,8,16 --iterations 100 \
    > $LOGS/cpu_train_scaling_$px.json"
done
# does the 3DGS step's thread-growing gap (results/speed/README.md, "Past two cores") go when numba's
# OpenMP workers keep spinning between kernels? per-stage profile at 16 threads, policies alternated
step cpu_wait_policy 150 bash -c "for p in default ACTIVE default ACTIVE; do echo \$p; w=OMP_WAIT_POLICY=ACTIVE; \
  [ \$p = ACTIVE ] || w=; env $CPU_ENV \$w python3 -m egobench.bench.cpu_profile --sigma 2.5 --repeats 15 \
  --threads \${CPU_PROFILE_THREADS:-16} --wall | tee -a $LOGS/cpu_wait_policy.json | grep -E 'step|glue|sum_of'; done"
step cpu_raster_scaling 150 bash -c "env $CPU_ENV python3 -m egobench.cli bench raster --backend cpu \
  --mode both --scaling 1,2,4,8,16 --repeats 7 > $LOGS/cpu_raster_scaling.json"
step bench_raster 45 bash -c "python3 -m egobench.cli bench raster --device cuda --mode both \
  --backend gsplat --backend torch --repeats 7 > $LOGS/bench_raster.json"
step bench_cast 60 bash -c "python3 -m egobench.cli bench cast --device cuda --side 512 --repeats 3 \
  --chunk 65536 --chunk 262144 --chunk 1048576 --chunk 4194304 --chunk 8388608 > $LOGS/bench_cast.json"
step bench_train 150 bash -c "python3 -m egobench.cli bench train --device cuda --resolution 2400 \
  --points 1000000 --iterations 30 > $LOGS/bench_train.json"
step sim_frames 150 python3 -m egobench.cli simulate --out /tmp/sim2400 --kind outdoor --seed 0 \
  --set n_frames=2 --set rectified_size=2400 --set compute_device=cuda
# the scale ladder (scripts/scale_ladder.py, docs/gpu-and-cluster.md), only where STEPS names it: it continues from
# the committed records (results/gpu/ladder/ladder.csv) and leaves them, with what ran, in OUT/ladder; by default
# on 1024 px recordings at 512 px (the CPU ladder's top rung, results/ladder/, on the GPU's rasterizer) and 1024 px
if [[ " ${STEPS:-} " == *" ladder "* ]]; then
  mkdir -p "$OUT/ladder"
  [[ -e "$OUT/ladder/ladder.csv" ]] || cp results/gpu/ladder/ladder.csv "$OUT/ladder/" 2>/dev/null
  step ladder "$(($(left) - 20))" python3 scripts/scale_ladder.py --out "$OUT/ladder" --work /tmp/ladder \
    --top "${LADDER_TOP:-1024}" --rungs "${LADDER_RUNGS:-512,1024}" --device cuda --budget-s "$(($(left) > 60 ? $(left) - 40 : 20))"
fi
SMOKE=$(($(left) - 30))
# a smoke run killed by its time limit leaves a lock; the next call unlocks and resumes it (frames, checkpoints)
# the jobs toward SMOKE_FIRST run first (default: the diagnosis, the one job no lease has finished);
# nvidia-smi samples the GPU's memory every 2 s meanwhile (gpu_memory.csv)
SMOKE_FIRST=${SMOKE_FIRST:-results/paper_smoke/diagnosis/bike_shop/ours}
MONITOR=
if wanted paper_smoke; then
  nvidia-smi --query-gpu=timestamp,memory.used,utilization.gpu --format=csv -l 2 >"$LOGS/gpu_memory.csv" 2>&1 &
  MONITOR=$!
fi
step paper_smoke "$SMOKE" bash -c "python3 -m snakemake --unlock --configfile config/paper_smoke.yaml >/dev/null 2>&1; \
  python3 -m snakemake --cores 16 --resources gpu=1 --keep-going --configfile config/paper_smoke.yaml \
  --prioritize $SMOKE_FIRST"
[[ -n $MONITOR ]] && kill "$MONITOR" 2>/dev/null

# what the smoke run left (small files only; recordings and checkpoints stay on the machine)
find results/paper_smoke .snakemake/log -type f \( -name '*.csv' -o -name '*.json' -o -name '*.tex' \
  -o -name '*.md' -o -name '*.log' -o -name '*.txt' \) -size -2M 2>/dev/null >"$LOGS/smoke_files.txt"
tar -czf "$OUT/logs.tar.gz" -C "$PWD" -T "$LOGS/smoke_files.txt" -C / "${LOGS#/}" 2>>"$OUT/summary.txt"
echo "total: $((SECONDS - START)) s" | tee -a "$OUT/summary.txt"
