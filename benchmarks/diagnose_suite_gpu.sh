#!/usr/bin/env bash
# The full `mosiv diagnose-suite` on the GPU machine, in calls of at most ~10 minutes:
#   source benchmarks/gpu_setup.sh && bash benchmarks/diagnose_suite_gpu.sh SECONDS JOBS BUDGET [ONLY]
# Runs the suite into /root/dsuite for SECONDS (entries already scored there are not redone, so
# calling it again resumes), then copies every entry's score and diagnosis report to $OUT.
seconds=${1:-540}
jobs=${2:-14}
budget=${3:-small}
only=${4:+--only $4}
mkdir -p /root/dsuite
timeout "$seconds" python3 -m mosiv_framework.cli.main diagnose-suite /root/dsuite \
  --jobs "$jobs" --budget "$budget" $only > /root/dsuite/suite_stdout.log 2>&1
echo "suite exit $? after $SECONDS s"
tail -5 /root/dsuite/suite_stdout.log
# one archive: the device returns a limited number of files
cd /root/dsuite && tar czf "$OUT/dsuite.tgz" suite.md suite.json suite_stdout.log \
  */score.json */diagnosis.md */diagnosis.json */metrics.json */suite.log 2>/dev/null
ls /root/dsuite/*/score.json 2>/dev/null | wc -l
