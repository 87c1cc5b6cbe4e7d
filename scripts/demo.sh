#!/usr/bin/env bash
# The demo on the tiny preset: generate data, evaluate every method under the paper's protocol,
# score the 3D segmentations (Table II), build the leaderboard and the 3-D report (inspect) under RUN_DIR/leaderboards
# and print the leaderboard.
# Usage: scripts/demo.sh [RUN_DIR]   (default runs/demo; every step resumes from what is on disk)
# Everything goes under RUN_DIR: the committed leaderboards/ are rebuilt only by `make leaderboards`.
set -euo pipefail
cd "$(dirname "$0")/.."
RUN=${1:-runs/demo}
BIN=.venv/bin
DATA=$RUN/data
RESULTS=$RUN/results

$BIN/generate_scenes --preset tiny --out "$DATA"
# Training set of the baselines trained on other objects (uois-sim, sdmaskrcnn-sim): none of tiny's objects.
TRAIN=$RUN/train-disjoint
$BIN/generate_scenes --preset tiny --object-pool cube,book,jar,egg,can_soup,chips_tube,flowerpot,hex_box --out "$TRAIN"

for m in one-segment fg-components depth-clustering lccp-frame oracle; do
  $BIN/evaluate --method "$m" --data "$DATA" --out "$RESULTS"
done
$BIN/evaluate --method supervised --data "$DATA" --config configs/supervised-tiny.yaml --out "$RESULTS"
# picie and stego train one network per fold; the demo runs their fold 0 only to stay near 20 minutes
# (the leaderboard's folds column says so). Drop --folds 0 for all three.
for m in picie stego; do
  $BIN/evaluate --method "$m" --data "$DATA" --config "configs/$m-tiny.yaml" --folds 0 --out "$RESULTS"
done
for m in uois-sim sdmaskrcnn-sim; do
  $BIN/evaluate --method "$m" --data "$DATA" --config "configs/$m-tiny.yaml" --set "train_data=$TRAIN" --out "$RESULTS"
done
for m in ours ours-v2 ours-v3 ours-v4; do
  $BIN/evaluate --method "$m" --data "$DATA" --config configs/ours-tiny.yaml --out "$RESULTS"
done
$BIN/evaluate3d --data "$DATA" --config configs/ours-tiny.yaml --out "$RESULTS"

BOARDS=$RUN/leaderboards
name=$($BIN/python -c "import sys; from selfseg.dataset import Dataset; print(Dataset(sys.argv[1]).name)" "$DATA")
# the 3-D report first: the leaderboard links it when it lies next to it
$BIN/inspect "$RESULTS" --dataset "$name" --out "$BOARDS/${name}_report.html"
$BIN/python -m selfseg.eval.leaderboard --results "$RESULTS" --out "$BOARDS"
cat "$BOARDS/$name.md"
echo "3-D report: xdg-open $BOARDS/${name}_report.html"
