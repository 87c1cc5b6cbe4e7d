#!/usr/bin/env bash
# The noisy-depth rows of a confirmation: the freeze's fresh seeds of PRESET-noisy (the same scenes with the
# depth-noise model on), each run once with the frozen code and configs of FROZEN, a clean checkout of the freeze
# (the one scripts/confirm.sh runs in; `confirm check` refuses any other). The key rows only: the geometric
# baselines, V2, ours, the supervised bound, sdmaskrcnn-sim (trained on the noisy disjoint-object set) and
# Table II, as jobs on both cores (scripts/queue.sh). Resumable; each seed goes to RUNS/seed-<S>, then
#   python -m selfseg.eval.confirm board --preset PRESET [--freeze NAME] --runs EXACT_RUNS --noisy-runs RUNS
# puts the drop exact − noisy beside the exact seeds. This script sequences the freeze's own commands; it may be
# newer than the freeze (the freeze's checkout need not have it).
# Usage: scripts/confirm_noisy.sh FROZEN RUNS [PRESET]   (PRESET: calibrated or cluttered; default calibrated;
# FREEZE=<preset>-N for a later freeze of the preset; SEEDS="S ..." for some of its seeds)
set -euo pipefail
HERE=$(cd "$(dirname "$0")" && pwd)
[ $# -ge 2 ] || { echo "usage: scripts/confirm_noisy.sh FROZEN RUNS [PRESET]" >&2; exit 2; }
FROZEN=$(cd "$1" && pwd)
mkdir -p "$2"
RUNS=$(cd "$2" && pwd)
PRESET=${3:-calibrated}
. "$HERE/disjoint_pool.sh"
. "$HERE/queue.sh"
disjoint_pool "$PRESET-noisy" || { echo "scripts/confirm_noisy.sh: no noisy variant of preset '$PRESET'" >&2; exit 2; }
cd "$FROZEN"
BIN=.venv/bin
FZ=(); [ -n "${FREEZE:-}" ] && FZ=(--freeze "$FREEZE")
ALL=$($BIN/python -m selfseg.eval.confirm seeds --preset "$PRESET" "${FZ[@]}")
# SEEDS="S ...": only these of the freeze's seeds. A seed another machine finished and archived is left out on a
# machine of another CPU type: its regenerated RGB differs there by a few 8-bit values (docs/reproducibility.md),
# so its records would not be kept and the seed would run a second time.
for seed in ${SEEDS:-}; do
  grep -qw "$seed" <<< "$ALL" || { echo "scripts/confirm_noisy.sh: seed $seed is not one of the freeze's:" $ALL >&2; exit 2; }
done
$BIN/python -m selfseg.eval.confirm check --preset "$PRESET" "${FZ[@]}"
OURS=configs/ours-$PRESET.yaml
SUP=configs/supervised-$PRESET.yaml
[ -f "$SUP" ] || SUP=configs/supervised-calibrated.yaml  # a preset without its own supervised config runs calibrated's

ev() {  # ev NAME METHOD ARGS...: one run under the protocol (3 folds), resuming finished folds; exit status 3 (a
  # fold failed under the budget its config declares: recorded in failed/, shown on the board) is an outcome
  local name=$1 m=$2; shift 2
  $BIN/evaluate --method "$m" --name "$name" --data "$DATA" --out "$RESULTS" --quiet "$@" || [ $? = 3 ]
}
job_geometric() { for m in fg-components depth-clustering lccp-frame oracle; do ev "$m" "$m" || return; done; }
job_ours-v2() { ev ours-v2 ours-v2 --config "$OURS"; }  # trains φ1, which ours and Table II read
# the first cluttered freeze ran no matching across scenes (its ours config had no node limit, and matching did not
# terminate on piles: docs/experiments/2026-11-26-cluttered-lccp.md), so no `ours` and Table II without its row;
# later cluttered freezes match under a node limit and a CPU budget
MATCHING=1; [ "$PRESET" = cluttered ] && [ -z "${FREEZE:-}" ] && MATCHING=0
job_ours() { [ $MATCHING = 0 ] || ev ours ours --config "$OURS"; }
job_supervised() { ev supervised supervised --config "$SUP"; }
job_generate-disjoint() {
  $BIN/generate_scenes --preset "$PRESET-noisy" "${OTHERS[@]}" --scenes 6 --seed 1 --out "$RUN/data-disjoint" --workers 2 --quiet
}
job_sdmaskrcnn-sim() { ev sdmaskrcnn-sim sdmaskrcnn-sim --set train_data="$RUN/data-disjoint"; }
job_evaluate3d() {
  local rows=(); [ $MATCHING = 1 ] || rows=(--rows lccp,lccp+symseg,gt-merging)
  $BIN/evaluate3d --data "$DATA" --config "$OURS" --out "$RESULTS" --quiet "${rows[@]}" || [ $? = 3 ]
}

for seed in ${SEEDS:-$ALL}; do
  echo "scripts/confirm_noisy.sh: $PRESET-noisy seed $seed ($(date -u +%FT%TZ))"
  RUN=$RUNS/seed-$seed
  DATA=$RUN/data
  RESULTS=$RUN/results
  $BIN/generate_scenes --preset "$PRESET-noisy" --seed "$seed" --out "$DATA" --workers 2 --quiet
  run_queue 2 "$RUN/logs" ours-v2 generate-disjoint sdmaskrcnn-sim:generate-disjoint ours:ours-v2 supervised \
    evaluate3d:ours-v2 geometric
  $BIN/python -m selfseg.eval.confirm check --preset "$PRESET" "${FZ[@]}"  # nothing moved while the seed ran
done
