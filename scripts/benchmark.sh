#!/usr/bin/env bash
# The benchmark preset (issue 9): generate the data, evaluate every method under the paper's protocol
# (3 folds), score the 3D segmentations (Table II) and rebuild leaderboards/benchmark.md.
# Usage: scripts/benchmark.sh [RUN_DIR]   (default runs/benchmark; every step resumes from what is on disk)
# Wall time of every step goes to RUN_DIR/timings.tsv.
set -euo pipefail
cd "$(dirname "$0")/.."
RUN=${1:-runs/benchmark}
BIN=.venv/bin
DATA=$RUN/data
DISJOINT=$RUN/data-disjoint
RESULTS=$RUN/results
mkdir -p "$RUN"
# Objects of the builtin library that the benchmark pool (generate/presets.py BENCHMARK_POOL) does not use.
OTHERS=box_large,box_small,book,cube,can_soup,chips_tube,jar,ball,egg,pill_tube,flowerpot,hex_box,cheese_wedge,pitcher,drill

step() {  # step NAME COMMAND...: run, append "NAME<TAB>seconds" to timings.tsv
  local name=$1; shift
  local t0=$SECONDS
  "$@"
  printf '%s\t%d\n' "$name" $((SECONDS - t0)) >> "$RUN/timings.tsv"
}

step generate $BIN/generate_scenes --preset benchmark --out "$DATA" --workers 2 --quiet
step generate-disjoint $BIN/generate_scenes --preset benchmark --object-pool "$OTHERS" --scenes 6 --seed 1 \
  --out "$DISJOINT" --workers 2 --quiet
for m in one-segment fg-components depth-clustering lccp-frame oracle; do
  step "$m" $BIN/evaluate --method "$m" --data "$DATA" --out "$RESULTS" --quiet
done
step supervised $BIN/evaluate --method supervised --data "$DATA" --config configs/supervised-benchmark.yaml \
  --out "$RESULTS" --quiet
step v1-disjoint $BIN/evaluate --method v1-disjoint --data "$DATA" --config configs/supervised-benchmark.yaml \
  --set train_data="$DISJOINT" --out "$RESULTS" --quiet
# Baselines E and F (default schedules; one training per fold) and B and D (trained once on the
# disjoint-object set with ground truth, tested zero-shot).
for m in picie stego; do
  step "$m" $BIN/evaluate --method "$m" --data "$DATA" --out "$RESULTS" --quiet
done
for m in uois-sim sdmaskrcnn-sim; do
  step "$m" $BIN/evaluate --method "$m" --data "$DATA" --set train_data="$DISJOINT" --out "$RESULTS" --quiet
done
for m in ours-v2 ours ours-v3 ours-v4; do
  step "$m" $BIN/evaluate --method "$m" --data "$DATA" --config configs/ours-benchmark.yaml --out "$RESULTS" --quiet
done
step evaluate3d $BIN/evaluate3d --data "$DATA" --config configs/ours-benchmark.yaml --out "$RESULTS"

$BIN/python -m selfseg.leaderboards.build --results "$RESULTS" --out leaderboards/
cat leaderboards/benchmark.md
