#!/usr/bin/env bash
# The confirmation protocol on a preset's fresh seeds (selfseg.eval.confirm has the rules):
#   1. commit every config, then  .venv/bin/python -m selfseg.eval.confirm freeze --preset calibrated
#      and commit leaderboards/calibrated-freeze.json at once (the seeds follow from the freeze commit's hash);
#   2. scripts/confirm.sh [RUNS] [PRESET]   (defaults runs/confirm, calibrated) in a clean checkout whose code and
#      configs are the freeze commit's: every fresh seed once (scripts/benchmark.sh with CONFIRM=1, resumable), then
#      the confirmation section of leaderboards/<PRESET>.md, with seed 0 beside it as a development seed.
# FREEZE=<preset>-N runs a later freeze of the preset (confirm freeze --freeze <preset>-N); default the first.
# Development continues elsewhere (another clone): this checkout must stay at the freeze while the seeds run.
set -euo pipefail
cd "$(dirname "$0")/.."
RUNS=${1:-runs/confirm}
PRESET=${2:-calibrated}
PY=.venv/bin/python
FZ=(); [ -n "${FREEZE:-}" ] && FZ=(--freeze "$FREEZE")
$PY -m selfseg.eval.confirm check --preset "$PRESET" "${FZ[@]}"
for seed in $($PY -m selfseg.eval.confirm seeds --preset "$PRESET" "${FZ[@]}"); do
  echo "scripts/confirm.sh: seed $seed ($(date -u +%FT%TZ))"
  SEED=$seed CONFIRM=1 scripts/benchmark.sh "$RUNS/seed-$seed" "$PRESET"
  $PY -m selfseg.eval.confirm check --preset "$PRESET" "${FZ[@]}"  # nothing moved while the seed ran
done
dev=()
[ -d "leaderboards/results/$PRESET" ] && dev=(--dev "seed 0=leaderboards/results/$PRESET")
$PY -m selfseg.eval.confirm board --preset "$PRESET" "${FZ[@]}" --runs "$RUNS" "${dev[@]}"
