#!/usr/bin/env bash
# Several variants of one training recipe, side by side on one GPU, each then evaluated: a GPU hour
# used to search for a CPU preset (issue 5's bar), since a recipe's learning does not depend on
# the hardware that runs it (only its wall time does).
#
#   1. every variant trains as its own process (`experiments.bipedal --preset PRESET` plus the
#      variant's --set overrides), all at once, each stopped by SIGTERM after TRAIN_S seconds (the
#      run saves a checkpoint and exits 143; it is then a prefix of the full curve);
#   2. every variant's latest checkpoint, and those saved at EVAL_ITERS, is evaluated with
#      EVAL_ARGS, all variants at once, each call under EVAL_S seconds.
# Results go under WORK; $OUT/sweep_results.tar.gz packs them without checkpoints, and
# $OUT/checkpoints.tar.gz holds each variant's latest checkpoint.
#
#   OUT=/tmp/sweep TRAIN_S=400 VARIANTS='base|;sigma01|--set env.reward_params.tracking_sigma=0.1' \
#     bash benchmarks/gpu_recipe_sweep.sh
set -u
OUT=${OUT:?set OUT to an empty results directory}
VARIANTS=${VARIANTS:?set VARIANTS to 'name|overrides;name|overrides;...'}
PY=${PY:-python3}
PRESET=${PRESET:-cpu}
COMMON_ARGS=${COMMON_ARGS:-}
TRAIN_S=${TRAIN_S:-400}
EVAL_S=${EVAL_S:-120}
EVAL_ARGS=${EVAL_ARGS:---push-interval 0 --episodes 128}
EVAL_ITERS=${EVAL_ITERS:-}
WORK=${WORK:-$(mktemp -d)}
export PYTHONUNBUFFERED=1 TQDM_MININTERVAL=${TQDM_MININTERVAL:-30}
# Several processes share the GPU: none may take most of its memory up front.
export XLA_PYTHON_CLIENT_PREALLOCATE=false
# shellcheck source=benchmarks/gpu_lib.sh
source "$(dirname "$0")/gpu_lib.sh"
OUT=$(abs_dir "$OUT") && WORK=$(abs_dir "$WORK") || exit 1
mkdir -p "$WORK/logs"
cd "$(dirname "$0")/.."
t0=$(date +%s)

machine_info "$PY" | tee "$WORK/logs/machine.txt"

names=()
IFS=';' read -ra specs <<< "$VARIANTS"
for spec in "${specs[@]}"; do
  name=${spec%%|*}; overrides=${spec#*|}
  names+=("$name")
  echo "== train $name: --preset $PRESET $COMMON_ARGS $overrides"
  # shellcheck disable=SC2086
  timeout -s TERM -k 30 "$TRAIN_S" $PY -m experiments.bipedal --preset "$PRESET" \
    --out "$WORK/$name" $COMMON_ARGS $overrides > "$WORK/logs/train_$name.log" 2>&1 &
done
wait
echo "== trained at $(( $(date +%s) - t0 ))s"
for name in "${names[@]}"; do
  echo "-- $name: $(grep -h 'finished\|interrupted\|Error' "$WORK/logs/train_$name.log" | tail -n 1 | cut -c1-200)"
done

for name in "${names[@]}"; do
  (
    for it in "" $EVAL_ITERS; do
      [ -n "$it" ] && flag="--iteration $it" || flag=""
      # shellcheck disable=SC2086
      timeout -s TERM "$EVAL_S" $PY -m experiments.evaluate --run "$WORK/$name" $EVAL_ARGS $flag \
        > "$WORK/logs/eval_${name}${it:+_it$it}.log" 2>&1
    done
  ) &
done
wait
echo "== evaluated at $(( $(date +%s) - t0 ))s"
for name in "${names[@]}"; do
  for m in "$WORK/$name"/eval*/metrics.json; do
    [ -f "$m" ] && $PY -c "import json,sys; m=json.load(open(sys.argv[1])); print(sys.argv[2], sys.argv[1].split('/')[-2], 'it', m.get('iteration'), 'fall', round(m['fall_rate'],3), 'speed', round(m['forward_speed'],3), 'C_limb', round(m['C_limb'],2))" "$m" "$name"
  done
done
tar -czf "$OUT/sweep_results.tar.gz" -C "$WORK" --exclude='*/checkpoints' --exclude='*/trajectories.npz' .
# Each variant's latest checkpoint too (small with checkpoint_env_state=false), so an evaluation
# the time limit cut can be run on another machine.
latest=()
for name in "${names[@]}"; do
  last=$(latest_step "$WORK/$name")
  [ -n "$last" ] && latest+=("$name/checkpoints/$last" "$name/config.json")
done
[ ${#latest[@]} -gt 0 ] && tar -czf "$OUT/checkpoints.tar.gz" -C "$WORK" "${latest[@]}"
ls -la "$OUT"
