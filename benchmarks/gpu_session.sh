#!/usr/bin/env bash
# What we measure on a lent GPU machine, in one bounded call:
#   1. a bipedal MASH training run at PRESET, stopped by SIGTERM after TRAIN_S seconds (the run saves
#      a checkpoint and exits 143; a shorter run than the preset is then a prefix of its curve);
#   2. its evaluation (DR on, 0.4 m/s), the ONNX export and sim-to-sim in MuJoCo C;
#   3. the benchmark (physics, env step, MASH / our PPO / Brax PPO training, compile) at BATCH, or
#      only BENCH_STAGES of it, once per MJX implementation of IMPLS (jax, warp), each within BENCH_S;
#   4. the batch sweep, for at most SWEEP_S and whatever time is left before DEADLINE_S.
# A stage whose limit is 0 is skipped (sim2sim exports the policy itself when EXPORT_S=0).
# Every stage has its own time limit and log; a failing stage does not stop the next. Results are
# written under WORK and packed into $OUT/gpu_results.tar.gz (everything but checkpoints) and
# $OUT/checkpoint.tar.gz (the run's latest checkpoint).
#
#   OUT=/tmp/gpu BATCH=8192 TRAIN_S=270 bash benchmarks/gpu_session.sh
set -u
OUT=${OUT:?set OUT to an empty results directory}
PY=${PY:-python3}
PRESET=${PRESET:-gpu}
BATCH=${BATCH:-8192}
BATCHES=${BATCHES:-1024,4096,16384}
BENCH_S=${BENCH_S:-130}
TRAIN_S=${TRAIN_S:-260}
EVAL_S=${EVAL_S:-60}
EXPORT_S=${EXPORT_S:-45}
SIM2SIM_S=${SIM2SIM_S:-$EXPORT_S}
SWEEP_S=${SWEEP_S:-600}
BENCH_STAGES=${BENCH_STAGES:-physics,env,mash,ppo,brax_ppo}
IMPLS=${IMPLS:-jax}
DEADLINE_S=${DEADLINE_S:-545}
EXTRA_TRAIN_ARGS=${EXTRA_TRAIN_ARGS:-}
EVAL_ARGS=${EVAL_ARGS:-}
export PYTHONUNBUFFERED=1 TQDM_MININTERVAL=${TQDM_MININTERVAL:-15}
SIM2SIM_ARGS=${SIM2SIM_ARGS:---episodes 4}
WORK=${WORK:-$(mktemp -d)}
# shellcheck source=benchmarks/gpu_lib.sh
source "$(dirname "$0")/gpu_lib.sh"
OUT=$(abs_dir "$OUT") && WORK=$(abs_dir "$WORK") || exit 1
mkdir -p "$WORK/logs"
t0=$(date +%s)
elapsed() { echo $(( $(date +%s) - t0 )); }

# stage NAME LIMIT_S CMD...: runs CMD under a time limit (SIGTERM, then SIGKILL 20 s later).
stage() {
  local name=$1 limit=$2; shift 2
  local left=$(( DEADLINE_S - $(elapsed) ))
  (( limit > left )) && limit=$left
  if (( limit < 20 )); then echo "== $name skipped: ${left}s left"; return; fi
  echo "== $name (limit ${limit}s, at $(elapsed)s)"
  timeout -s TERM -k 20 "$limit" "$@" > "$WORK/logs/$name.log" 2>&1
  echo "== $name rc=$? at $(elapsed)s"
  tail -n 4 "$WORK/logs/$name.log" | cut -c1-300
}

machine_info "$PY" | tee "$WORK/logs/machine.txt"

cd "$(dirname "$0")/.."
stage train "$TRAIN_S" $PY -m experiments.bipedal --preset "$PRESET" --out "$WORK/run" \
  $EXTRA_TRAIN_ARGS
grep -h "iteration" "$WORK/logs/train.log" | tail -n 2
stage evaluate "$EVAL_S" $PY -m experiments.evaluate --run "$WORK/run" $EVAL_ARGS
stage export "$EXPORT_S" $PY -m experiments.export --run "$WORK/run"
stage sim2sim "$SIM2SIM_S" $PY -m experiments.sim2sim --run "$WORK/run" $SIM2SIM_ARGS
for impl in ${IMPLS//,/ }; do
  stage "benchmark_$impl" "$BENCH_S" $PY -m experiments.benchmark --quick --batch "$BATCH" \
    --stages "$BENCH_STAGES" --impl "$impl" --out "$WORK/benchmark_$impl.json"
done
stage sweep "$SWEEP_S" $PY -m experiments.benchmark --sweep batch --batches "$BATCHES" --dir "$WORK"

cp "$WORK/logs/machine.txt" "$WORK/run/" 2>/dev/null
tar -czf "$OUT/gpu_results.tar.gz" -C "$WORK" --exclude=run/checkpoints logs \
  $(cd "$WORK" && ls -d run benchmark_*.json scaling_batch.* 2>/dev/null)
last=$(latest_step "$WORK/run")
[ -n "$last" ] && tar -czf "$OUT/checkpoint.tar.gz" -C "$WORK" "run/checkpoints/$last"
ls -la "$OUT"
[ -f "$WORK/run/eval/metrics.json" ] && cat "$WORK/run/eval/metrics.json" | head -c 1500
for f in "$WORK"/benchmark_*.json; do [ -f "$f" ] && echo && head -c 2000 "$f"; done
echo "== done at $(elapsed)s"
