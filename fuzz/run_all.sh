#!/usr/bin/env bash
# The long coverage-guided runs: every cargo-fuzz target for SECONDS (default 600)
# each, new inputs in fuzz/work/<target> (ignored), findings in
# fuzz/artifacts/<target>/, one log per target in fuzz/logs/ (ignored).
# Usage: bash fuzz/run_all.sh [SECONDS] [TARGET...]   (needs nightly + cargo-fuzz)
set -euo pipefail
cd "$(dirname "$0")/.."
secs=${1:-600}
shift || true
targets=("$@")
[ ${#targets[@]} -gt 0 ] || mapfile -t targets < <(cargo +nightly fuzz list)
mkdir -p fuzz/logs
for t in "${targets[@]}"; do
  mkdir -p "fuzz/work/$t"
  if cargo +nightly fuzz run --sanitizer none --debug-assertions "$t" "fuzz/work/$t" "fuzz/corpus/$t" -- \
      -max_total_time="$secs" -malloc_limit_mb=512 -rss_limit_mb=2048 -timeout=10 -print_final_stats=1 \
      > "fuzz/logs/$t.log" 2>&1; then
    status=ok
  else
    status=FINDING
  fi
  runs=$(grep -o 'stat::number_of_executed_units: *[0-9]*' "fuzz/logs/$t.log" | grep -o '[0-9]*$' || echo "?")
  echo "$t: $status, $runs executions in ${secs} s"
done
