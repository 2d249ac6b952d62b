#!/usr/bin/env bash
# On the GPU machine (after `bash ../shared/gpu/bundle.sh` and `bash scripts/gpu-extras.sh` here):
# the shared check (install, env, smoke, the suite on cuda_ad_rgb, a short optimize) in a shortened
# budget, then issue 38's iteration breakdown, traced and with the recorded part
# (benchmarks/iteration_time.py --freeze both) on cuda_ad_rgb. Device call: carry [".gpu"],
# command `bash scripts/gpu-iteration.sh`, timeout_s 570.
set -uo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
: "${OUT:=/tmp/psdr-gpu-out}"
export OUT
: "${CHECK_STEPS:=env smoke tests optimize}"
: "${CHECK_BUDGET_S:=330}"
: "${T_ITERATION:=190}"
STEPS="$CHECK_STEPS" BUDGET_S="$CHECK_BUDGET_S" T_TESTS="${T_TESTS:-170}" bash .gpu/psdr-check.sh
echo "=== iteration breakdown (cuda_ad_rgb), at most ${T_ITERATION}s"
export PYTHONPATH="/tmp/site:$PWD:$PWD/.gpu/stub"
timeout "$T_ITERATION" python3 benchmarks/iteration_time.py --scales 1,2 --freeze both --warmup 4 \
    --iterations 10 --label cuda --json "$OUT/iteration_cuda_frozen.json" 2>&1 | tee "$OUT/iteration.log"
echo "iteration breakdown exit: ${PIPESTATUS[0]}"
