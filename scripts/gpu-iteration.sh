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
: "${ITERATION_ARGS:=--scales 1,2 --freeze both --warmup 4 --iterations 10}"
: "${LOOP_ROUNDS:=0}"           # >0: also benchmarks/frozen_loop.py (psdr optimize, frozen and traced alternated)
: "${LOOP_ITERATIONS:=80}"
: "${T_LOOP:=200}"
STEPS="$CHECK_STEPS" BUDGET_S="$CHECK_BUDGET_S" T_TESTS="${T_TESTS:-170}" bash .gpu/psdr-check.sh
export PYTHONPATH="/tmp/site:$PWD:$PWD/.gpu/stub"
# what check.sh set up for its own steps: the carried system libraries, OptiX, libLLVM
export LD_LIBRARY_PATH="/tmp/syslib:/usr/local/nvidia/lib64${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
llvm=$(sed -n 's/^libLLVM: \(\S*\).*/\1/p' "$OUT/env.txt" 2>/dev/null | head -1)
[ -n "$llvm" ] && [ -z "${DRJIT_LIBLLVM_PATH:-}" ] && export DRJIT_LIBLLVM_PATH="$llvm"
if [ "$LOOP_ROUNDS" -gt 0 ]; then
    echo "=== psdr optimize, frozen and traced (cuda_ad_rgb), at most ${T_LOOP}s"
    PSDR_VARIANT=cuda_ad_rgb timeout "$T_LOOP" python3 benchmarks/frozen_loop.py --rounds "$LOOP_ROUNDS" \
        --iterations "$LOOP_ITERATIONS" --json "$OUT/frozen_loop_cuda.json" 2>&1 | tee "$OUT/frozen_loop.log"
fi
echo "=== iteration breakdown (cuda_ad_rgb), at most ${T_ITERATION}s"
# shellcheck disable=SC2086
timeout "$T_ITERATION" python3 benchmarks/iteration_time.py $ITERATION_ARGS --label cuda \
    --json "$OUT/iteration_cuda_frozen.json" 2>&1 | tee "$OUT/iteration.log"
echo "iteration breakdown exit: ${PIPESTATUS[0]}"
