#!/usr/bin/env bash
# Go on with a freeze's fresh seeds on this machine, from what an earlier machine archived: a clean clone of the
# freeze (its record commit: the freeze's code and configs plus the record) in CLONE, installed; the archived fold
# records (`confirm archive`, committed under leaderboards/results/) restored into RUNS; then the freeze's own
# scripts/confirm.sh (or, with NOISY=1, this checkout's scripts/confirm_noisy.sh on the freeze's clone) in the
# background, keeping every restored fold (KEEP_EARLIER=1) and running only what is missing. The data is generated
# again; a kept fold counts only where it has the content hash its record names.
# Usage: [NOISY=1] scripts/confirm_resume.sh PRESET FREEZE CLONE RUNS   (FREEZE: the preset's name for its first
# freeze, <preset>-N for a later one; with NOISY=1, SEEDS="S ..." runs only those of its seeds, see
# scripts/confirm_noisy.sh). Prints where the run's log goes; archive again before the machine ends:
#   .venv/bin/python -m selfseg.eval.confirm archive --preset PRESET --freeze FREEZE --runs RUNS [--noisy]
set -euo pipefail
[ $# = 4 ] || { echo "usage: scripts/confirm_resume.sh PRESET FREEZE CLONE RUNS" >&2; exit 2; }
PRESET=$1 FREEZE=$2 CLONE=$3 RUNS=$4
HERE=$(cd "$(dirname "$0")/.." && pwd)
RECORD=leaderboards/$FREEZE-freeze.json
[ -f "$HERE/$RECORD" ] || { echo "scripts/confirm_resume.sh: $HERE/$RECORD: no such freeze record" >&2; exit 2; }
AT=$(git -C "$HERE" log -1 --format=%H --diff-filter=A -- "$RECORD")
if [ ! -d "$CLONE/.git" ]; then
  git clone -q "$HERE" "$CLONE"
  git -C "$CLONE" checkout -q "$AT"
fi
mkdir -p "$RUNS"
make -C "$CLONE" install > "$RUNS/install.log" 2>&1 ||  # the clone stays clean: a frozen checkout may hold nothing new
  { echo "scripts/confirm_resume.sh: make install failed in $CLONE (see $RUNS/install.log)" >&2; exit 1; }
# a first freeze goes without --freeze / FREEZE=, as its own (older) scripts expect
FZ=() FZ_ENV=(); [ "$FREEZE" != "$PRESET" ] && FZ=(--freeze "$FREEZE") FZ_ENV=(FREEZE="$FREEZE")
NOISY_ARG=(); [ "${NOISY:-0}" = 1 ] && NOISY_ARG=(--noisy)
"$HERE/.venv/bin/python" -m selfseg.eval.confirm restore --preset "$PRESET" "${FZ[@]}" --runs "$RUNS" "${NOISY_ARG[@]}"
"$CLONE/.venv/bin/python" -m selfseg.eval.confirm check --preset "$PRESET" "${FZ[@]}"
LOG=$RUNS/confirm.log
if [ "${NOISY:-0}" = 1 ]; then
  env "${FZ_ENV[@]}" setsid nohup "$HERE/scripts/confirm_noisy.sh" "$CLONE" "$RUNS" "$PRESET" >> "$LOG" 2>&1 < /dev/null &
else
  (cd "$CLONE" && env "${FZ_ENV[@]}" KEEP_EARLIER=1 setsid nohup scripts/confirm.sh "$RUNS" "$PRESET" >> "$LOG" 2>&1 < /dev/null &)
fi
echo "scripts/confirm_resume.sh: $FREEZE running from $CLONE ($(git -C "$CLONE" rev-parse --short HEAD)); log $LOG"
