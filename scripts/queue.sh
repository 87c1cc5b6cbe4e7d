# run_queue SLOTS LOGDIR SPEC...: a job queue for bash scripts (sourced by scripts/benchmark.sh and scripts/demo.sh).
# Each SPEC is NAME or NAME:DEP,DEP,...; job NAME is the shell function job_NAME, its output goes to LOGDIR/NAME.log.
# At most SLOTS jobs run at once. Whenever a slot is free, the first job in SPEC order whose dependencies have all
# finished starts, so SPEC lists the jobs longest first (after those that gate others). After a failure no new job
# starts; once the running ones have ended it returns 1. Prints a line as each job starts and ends.
run_queue() {
  local slots=$1 logdir=$2; shift 2
  local -a names=() deps=()
  local -A state=() by_pid=()
  local spec name d i ok pid rc running=0 failed=0
  for spec in "$@"; do
    name=${spec%%:*}
    names+=("$name")
    if [[ $spec == *:* ]]; then deps+=("${spec#*:}"); else deps+=(""); fi
    state[$name]=pending
  done
  for i in "${!names[@]}"; do
    for d in ${deps[$i]//,/ }; do
      [ -n "${state[$d]:-}" ] || { echo "run_queue: job ${names[$i]} needs $d, which is not a job" >&2; return 2; }
    done
    declare -F "job_${names[$i]}" > /dev/null || { echo "run_queue: no function job_${names[$i]}" >&2; return 2; }
  done
  mkdir -p "$logdir"
  while :; do
    if [ $failed = 0 ]; then
      for i in "${!names[@]}"; do
        [ $running -lt "$slots" ] || break
        name=${names[$i]}
        [ "${state[$name]}" = pending ] || continue
        ok=1
        for d in ${deps[$i]//,/ }; do [ "${state[$d]}" = done ] || ok=0; done
        [ $ok = 1 ] || continue
        "job_$name" > "$logdir/$name.log" 2>&1 &
        by_pid[$!]=$name
        state[$name]=running
        running=$((running + 1))
        echo "run_queue: $name started $(date -u +%T)"
      done
    fi
    [ $running -gt 0 ] || break
    rc=0
    wait -n -p pid || rc=$?
    name=${by_pid[$pid]}
    running=$((running - 1))
    if [ $rc = 0 ]; then
      state[$name]=done
      echo "run_queue: $name done $(date -u +%T)"
    else
      state[$name]=failed
      failed=1
      echo "run_queue: $name failed (exit $rc); see $logdir/$name.log" >&2
    fi
  done
  return $failed
}
