#!/usr/bin/env bash
# A preset's leaderboard (benchmark or calibrated): generate the data, evaluate every method under the paper's protocol
# (3 folds), score the 3D segmentations (Table II) and rebuild leaderboards/<dataset>.md.
# Usage: scripts/benchmark.sh [RUN_DIR] [PRESET]   (defaults runs/benchmark, benchmark; PRESET is benchmark,
# calibrated, cluttered or their -noisy variants; every step resumes from what is on disk). The runs are jobs of a
# queue with one worker per core (torch uses one thread per process; scripts/queue.sh), each logged to
# RUN_DIR/logs/<job>.log; the wall and CPU time and peak memory of every step go to RUN_DIR/timings.tsv, the run's
# wall time as its last row (`total`); bench/profile_run.py reads them.
# KEEP_EARLIER=1 finishes a run over several sessions: a method whose folds of this dataset (same content hash) are
# already in RUN_DIR/results with the config it would run with now, from whatever commit, is not run again (the
# leaderboard's Runs table names each run's commit); a method whose config changed runs again and replaces the
# earlier run (`evaluate --replace`). Without it a method's finished folds are reused only at the same commit and
# config, as `evaluate` does.
# SEED=S generates the preset at dataset seed S (default 0). SKIP="name ..." leaves those runs (or evaluate3d) out. CONFIRM=1 is the
# confirmation protocol's subset (scripts/confirm.sh): no PiCIE, STEGO, V1, one-segment or the GT-merging diagnostic,
# and no leaderboard rebuild (the confirmation board pools the seeds instead).
set -euo pipefail
cd "$(dirname "$0")/.."
RUN=${1:-runs/benchmark}
PRESET=${2:-benchmark}
BIN=.venv/bin
DATA=$RUN/data
DISJOINT=$RUN/data-disjoint
RESULTS=$RUN/results
SEED=${SEED:-0}
CONFIRM=${CONFIRM:-0}
[ "$CONFIRM" = 1 ] && SKIP=${SKIP:-one-segment v1-disjoint ours-gt-merging picie stego}
SKIP=" ${SKIP:-} "
BASE=${PRESET%-noisy}
# `ours` with the paper's pruning: c_del = α = .1 (criterion 1), registration P/R ≥ .9 (criterion 2) and the
# paper's criterion 3 (its witnesses at that threshold, no isolation cover), on the preset's config otherwise.
PAPER_PRUNING=(--set pseudo.match.c_del_node=0.1 --set pseudo.match.c_del_edge=0.1 --set pseudo.prune.alpha=0.1
               --set pseudo.prune.pr_thresh=0.9 --set pseudo.prune.witness_pr_thresh=null
               --set pseudo.prune.isolation_cover=null)
# The methods' configs: a noisy variant runs its preset's (not re-tuned on noise, so the drop is the noise's
# doing); a preset without its own file of a method (cluttered's supervised) runs calibrated's.
config() {  # config METHOD: the YAML file METHOD runs with on this preset
  if [ -f "configs/$1-$BASE.yaml" ]; then echo "configs/$1-$BASE.yaml"; else echo "configs/$1-calibrated.yaml"; fi
}
SUP=$(config supervised)
OURS=$(config ours)
mkdir -p "$RUN"
START=$SECONDS
# The disjoint-object training set of baselines B and D and of v1-disjoint (scripts/disjoint_pool.sh).
. scripts/disjoint_pool.sh
disjoint_pool "$PRESET" || {
  echo "scripts/benchmark.sh: unknown preset '$PRESET' (benchmark, calibrated, cluttered, or calibrated-noisy, cluttered-noisy)" >&2; exit 2; }

step() {  # step NAME COMMAND...: run it; append "NAME<TAB>wall s<TAB>CPU s<TAB>peak MB" to timings.tsv (CPU: user +
  # system of the command and every process it waited for; peak: the largest resident set among them)
  local name=$1; shift
  $BIN/python - "$RUN/timings.tsv" "$name" "$@" <<'PY'
import resource, subprocess, sys, time
tsv, name, cmd = sys.argv[1], sys.argv[2], sys.argv[3:]
t0 = time.monotonic()
rc = subprocess.run(cmd, stdin=subprocess.DEVNULL).returncode
if rc in (0, 3):  # 3: a fold failed under its budget, recorded (failed/) like a result
    u = resource.getrusage(resource.RUSAGE_CHILDREN)
    with open(tsv, "a") as f:
        f.write(f"{name}\t{time.monotonic() - t0:.0f}\t{u.ru_utime + u.ru_stime:.0f}\t{u.ru_maxrss / 1024:.0f}\n")
sys.exit(rc)
PY
}

step generate $BIN/generate_scenes --preset "$PRESET" --seed "$SEED" --out "$DATA" --workers 2 --quiet
# The folder this dataset's scores are filed under in RESULTS (its name, or name-hash beside another dataset's).
KEY=$($BIN/python -c 'import sys; from pathlib import Path; from selfseg.dataset import Dataset
from selfseg.eval.layout import results_key; print(results_key(Path(sys.argv[1]), Dataset(sys.argv[2])))' "$RESULTS" "$DATA")

kept() {  # kept NAME N METHOD [--config FILE] [--set K=V ...]: KEEP_EARLIER is set and run NAME has N fold files of
  # this dataset in RESULTS (scores, or failures under a budget), every one recorded with the config hash METHOD has
  # under these arguments now (a changed config runs again)
  [ "${KEEP_EARLIER:-0}" = 1 ] || return 1
  local name=$1 n=$2; shift 2
  $BIN/python - "$RESULTS/scores/$KEY/$name" "$RESULTS/failed/$KEY/$name" "$n" "$@" <<'PY' || return 1
import sys
from pathlib import Path
from selfseg.config import config_hash, load_config
from selfseg.eval.cli import build_parser
from selfseg.fileio import read_json
from selfseg.registry import get_method_class
scores, failed, n = Path(sys.argv[1]), Path(sys.argv[2]), int(sys.argv[3])
args = build_parser().parse_args(["--method", *sys.argv[4:]])  # evaluate's own reading of the arguments
want = config_hash(load_config(get_method_class(args.method).config_cls, args.config, args.overrides))
# a fold that failed under its budget counts as done: it is not run again (selfseg.eval.resume)
found = [read_json(f)["config_hash"] for d in (scores, failed) for f in sorted(d.glob("fold*.json"))]
sys.exit(0 if len(found) >= n and set(found) == {want} else 1)
PY
  echo "scripts/benchmark.sh: $name: kept from an earlier run with this config (KEEP_EARLIER=1)"
}

skipped() {  # skipped NAME: NAME is in SKIP
  [[ "$SKIP" == *" $1 "* ]]
}

evaluate_as() {  # evaluate_as NAME METHOD ARGS...: one run of a method under its own name, 3 folds
  local name=$1 m=$2; shift 2
  skipped "$name" && return 0
  kept "$name" 3 "$m" "$@" && return 0
  local replace=(); [ "${KEEP_EARLIER:-0}" = 1 ] && replace=(--replace)
  step "$name" $BIN/evaluate --method "$m" --name "$name" --data "$DATA" --out "$RESULTS" --quiet "${replace[@]}" "$@" ||
    over_budget $? "$name"
}

over_budget() {  # over_budget RC NAME: exit status 3 (a fold, or a Table II row, failed under the budget its config
  # declares) is an outcome, recorded in RESULTS/failed/ and shown on the boards, not a failure of the queue
  [ "$1" = 3 ] || return "$1"
  echo "scripts/benchmark.sh: $2: failed under its budget (recorded in $RESULTS/failed/)"
}

evaluate() {  # evaluate METHOD ARGS...: one method under its own name
  evaluate_as "$1" "$@"
}

# The runs as jobs of a queue (scripts/queue.sh) with one worker per core (torch uses one thread per process).
job_geometric() {  # the geometric baselines and the oracle: a minute together
  for m in one-segment fg-components depth-clustering lccp-frame oracle; do evaluate "$m" || return; done
}
job_supervised() { evaluate supervised --config "$SUP"; }
# V2 trains φ1 (its final network) per fold; ours, V3, V4 and the paper's pruning then read φ1 and its segment
# features from the stage cache, and the other runs on the per-video stages find them built.
job_ours-v2() { evaluate ours-v2 --config "$OURS"; }
job_ours() { evaluate ours --config "$OURS"; }
job_ours-v3() { evaluate ours-v3 --config "$OURS"; }
job_ours-v4() { evaluate ours-v4 --config "$OURS"; }
job_ours-paper-pruning() {  # left out where the preset's `ours` already prunes as the paper does (it is that row)
  if $BIN/python - "$OURS" "${PAPER_PRUNING[@]}" <<'PY'; then
import sys
from selfseg.config import load_config
from selfseg.method.pipeline import OursConfig
path, sets = sys.argv[1], [a for a in sys.argv[2:] if a != "--set"]
sys.exit(0 if load_config(OursConfig, path) == load_config(OursConfig, path, sets) else 1)
PY
    echo "scripts/benchmark.sh: ours-paper-pruning left out: $OURS already prunes as the paper does"
    return 0
  fi
  evaluate_as ours-paper-pruning ours --config "$OURS" "${PAPER_PRUNING[@]}"
}
# ours-gt-merging (a diagnostic that reads ground truth): φ2 as in ours on the over-segments merged by ground
# truth, so ours-gt-merging − ours-v2 is the most a perfect matching and pruning step could add in Table I.
job_ours-gt-merging() { evaluate ours-gt-merging --config "$OURS"; }
job_evaluate3d() {  # Table II
  skipped evaluate3d && return 0
  kept ours-matching 1 ours --config "$OURS" ||
    step evaluate3d $BIN/evaluate3d --data "$DATA" --config "$OURS" --out "$RESULTS" || over_budget $? evaluate3d
}
job_generate-disjoint() {  # while v1-disjoint, uois-sim or sdmaskrcnn-sim is to run (neither skipped nor kept)
  local need=0
  skipped v1-disjoint || kept v1-disjoint 3 v1-disjoint --config "$SUP" --set train_data="$DISJOINT" || need=1
  skipped uois-sim || kept uois-sim 3 uois-sim --set train_data="$DISJOINT" || need=1
  skipped sdmaskrcnn-sim || kept sdmaskrcnn-sim 3 sdmaskrcnn-sim --set train_data="$DISJOINT" || need=1
  [ $need = 0 ] || step generate-disjoint $BIN/generate_scenes --preset "$PRESET" "${OTHERS[@]}" --scenes 6 --seed 1 \
    --out "$DISJOINT" --workers 2 --quiet
}
# Baselines B and D and V1, trained once on the disjoint-object set with ground truth, tested zero-shot.
job_v1-disjoint() { evaluate v1-disjoint --config "$SUP" --set train_data="$DISJOINT"; }
job_uois-sim() { evaluate uois-sim --set train_data="$DISJOINT"; }
job_sdmaskrcnn-sim() { evaluate sdmaskrcnn-sim --set train_data="$DISJOINT"; }
job_picie() { evaluate picie; }
job_stego() { evaluate stego; }

. scripts/queue.sh
# Priority order: the jobs that others wait for, then the longest first (calibrated, 2 cores: STEGO 93 min,
# SD-MaskRCNN 80, the GT-merging diagnostic 70, ours 60, V4 55, PiCIE 49, supervised 42, V1 40, UOIS 23-38,
# V3 35, the paper's pruning 35, Table II 15); the geometric runs fill the end.
# (called plainly, not in a condition: bash ignores set -e inside a condition, and in the jobs it starts)
run_queue 2 "$RUN/logs" ours-v2 generate-disjoint stego sdmaskrcnn-sim:generate-disjoint \
  ours-gt-merging:ours-v2 ours:ours-v2 ours-v4:ours-v2 picie supervised v1-disjoint:generate-disjoint \
  uois-sim:generate-disjoint ours-v3:ours-v2 ours-paper-pruning:ours-v2 evaluate3d:ours-v2 geometric
printf 'total\t%d\t\t\n' $((SECONDS - START)) >> "$RUN/timings.tsv"

[ "$CONFIRM" = 1 ] || $BIN/python -m selfseg.eval.leaderboard --results "$RESULTS" --out leaderboards/
