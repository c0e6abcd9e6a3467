#!/usr/bin/env bash
# Long GPU work spread over several device calls (each call is limited to 10 minutes).
# For more jobs than the GPUs serve well at once, or jobs that import modules lazily, start them
# with benchmarks/device_queue.py instead (slots per GPU, a snapshot of the checkout per job);
# `wait` below serves both.
# Jobs started here run in their own process session (setsid), so they outlive the call that
# started them for as long as the machine stays warm: make the next call within its idle window.
#
#   source benchmarks/gpu_setup.sh
#   bash benchmarks/device_batch.sh start NAME COMMAND...   # background; log ~/jobs/NAME.log
#   bash benchmarks/device_batch.sh wait SECONDS ['GLOB'...]  # until every job ends or SECONDS
#                                                           # pass; then pack the logs, exit
#                                                           # codes and GLOBs into $OUT/batch.tgz
# Quote the GLOBs: they are expanded when the waiting ends, so files the jobs wrote meanwhile
# are packed too (a glob the calling shell expands misses them).
# Don't pipe a script that starts jobs into tail or grep: the jobs inherit the pipe, so the call
# waits for them all and runs into its time limit (they go on, but its output is lost).
# Give the jobs an output folder outside $OUT: the device empties $OUT before each call, so a
# job writing there loses what it wrote before the call that is running now.
jobs_dir=${DEVICE_JOBS_DIR:-$HOME/jobs}
mkdir -p "$jobs_dir"
verb=$1
shift
case "$verb" in
start)
  name=$1
  shift
  # the exit code lands in NAME.rc when the job ends, which is how `wait` knows it has
  setsid bash -c '"$@" > '"$jobs_dir/$name.log"' 2>&1; echo $? > '"$jobs_dir/$name.rc" \
    _ "$@" < /dev/null &
  echo "started $name (pid $!)"
  ;;
wait)
  seconds=$1
  shift
  start=$SECONDS
  while ((SECONDS - start < seconds)); do
    running=0
    for log in "$jobs_dir"/*.log; do
      [ -e "${log%.log}.rc" ] || running=$((running + 1))
    done
    # jobs that benchmarks/device_queue.py holds back until a slot is free
    for mark in "$jobs_dir"/*.queued; do
      [ -e "$mark" ] && running=$((running + 1))
    done
    ((running == 0)) && break
    sleep 10
  done
  for log in "$jobs_dir"/*.log; do
    name=$(basename "${log%.log}")
    rc=$(cat "${log%.log}.rc" 2>/dev/null || echo running)
    echo "== $name: $rc; $(tail -c 300 "$log" | tr '\r\n' '  ' | tail -c 200)"
  done
  for mark in "$jobs_dir"/*.queued; do
    [ -e "$mark" ] && echo "== $(basename "${mark%.queued}"): queued"
  done
  nvidia-smi --query-gpu=name,utilization.gpu,memory.used --format=csv,noheader
  files=()
  for pattern in "$@"; do
    while IFS= read -r match; do files+=("$match"); done < <(compgen -G "$pattern")
  done
  # the logs and exit codes, not the queue's checkout snapshots (too big to come back)
  tar czf "$OUT/batch.tgz" --exclude='checkout-*' --exclude='*.tree' "$jobs_dir" "${files[@]}" \
    2>/dev/null
  ls -la "$OUT"
  ;;
*)
  echo "usage: device_batch.sh start NAME COMMAND... | wait SECONDS ['GLOB'...]" >&2
  exit 2
  ;;
esac
