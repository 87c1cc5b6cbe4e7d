#!/usr/bin/env bash
# The demo on the demo preset (6 videos of toys spread on a table, 160×120, seconds per network): generate the
# data; evaluate, two runs at a time (one per core), the method, its over-segment-only ablation (V2), the
# supervised bound and the geometric baselines under the paper's protocol (3 folds); score the 3-D segmentations
# (Table II); build the leaderboard and the 3-D report (inspect) under RUN_DIR/leaderboards; print the leaderboard
# and the paired claims (ours − V2, ours − depth-clustering: 95 % CIs over the 6 test videos and whether they are
# inside the noise); then open the report where a desktop is available. The paper's other baselines (PiCIE, STEGO,
# UOIS, SD-MaskRCNN) and V3/V4 run in scripts/benchmark.sh on the larger presets; the CI's preset is tiny.
# Usage: scripts/demo.sh [RUN_DIR]   (default runs/demo; every step resumes from what is on disk)
# Everything goes under RUN_DIR: the committed leaderboards/ are rebuilt only by `make leaderboards`.
set -euo pipefail
cd "$(dirname "$0")/.."
RUN=${1:-runs/demo}
BIN=.venv/bin
DATA=$RUN/data
RESULTS=$RUN/results

$BIN/generate_scenes --preset demo --out "$DATA" --workers 2
# The runs as jobs on both cores (scripts/queue.sh; each method trains with one thread): V2 trains φ1, which ours
# reads; each job's output goes to RUN_DIR/logs/<job>.log.
job_geometric() {
  for m in one-segment fg-components depth-clustering lccp-frame oracle; do
    $BIN/evaluate --method "$m" --data "$DATA" --out "$RESULTS" || return
  done
}
job_supervised() { $BIN/evaluate --method supervised --data "$DATA" --config configs/supervised-demo.yaml --out "$RESULTS"; }
job_ours-v2() { $BIN/evaluate --method ours-v2 --data "$DATA" --config configs/ours-demo.yaml --out "$RESULTS"; }
job_ours() { $BIN/evaluate --method ours --data "$DATA" --config configs/ours-demo.yaml --out "$RESULTS"; }
job_evaluate3d() { $BIN/evaluate3d --data "$DATA" --config configs/ours-demo.yaml --out "$RESULTS"; }
. scripts/queue.sh
run_queue 2 "$RUN/logs" ours-v2 supervised ours:ours-v2 evaluate3d:ours-v2 geometric

BOARDS=$RUN/leaderboards
name=$($BIN/python -c "import sys; from selfseg.dataset import Dataset; print(Dataset(sys.argv[1]).name)" "$DATA")
# the 3-D report first: the leaderboard links it when it lies next to it
$BIN/inspect "$RESULTS" --dataset "$name" --out "$BOARDS/${name}_report.html"
$BIN/python -m selfseg.eval.leaderboard --results "$RESULTS" --out "$BOARDS"
cat "$BOARDS/$name.md"
echo
echo "Paired claims on this seed (a difference is a result only when its CI excludes 0):"
$BIN/python -m selfseg.eval.confirm compare --results "$RESULTS" --b ours-v2 --b depth-clustering
report=$BOARDS/${name}_report.html
if [ -n "${DISPLAY:-}${WAYLAND_DISPLAY:-}" ] && command -v xdg-open > /dev/null; then
  xdg-open "$report" > /dev/null 2>&1 &
  echo "3-D report opened: $report"
else
  echo "3-D report: xdg-open $report"
fi
