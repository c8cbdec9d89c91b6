#!/usr/bin/env bash
# The main job's speed as a user sees it: runs `icrl pretrain --env ENV` (its
# default preset, plus any further arguments) from scratch, samples the
# process's CPU time (every thread) and the updates logged in metrics.jsonl
# every 2 s, stops the run (SIGINT) after T1 seconds and prints the cores
# kept busy and the updates per second between T0 and T1. The rate is read
# between the first and last change of the logged update count in the window
# (metrics are written once per collection round).
#
# usage: icrl/benches/pretrain_speed.sh NAME T0 T1 ENV [pretrain arguments...]
# e.g.   icrl/benches/pretrain_speed.sh car 60 300 car --set learner_threads=1
# Needs a release build (cargo build --release -p icrl) and an idle machine.
set -euo pipefail
name=$1 t0=$2 t1=$3 env=$4
shift 4
root=$(cd "$(dirname "$0")/../.." && pwd)
out=${ICRL_SPEED_OUT:-/tmp/icrl-speed}/$name
rm -rf "$out" && mkdir -p "$out"
"$root/target/release/icrl" pretrain --env "$env" --out "$out" "$@" >"$out/log.txt" 2>&1 &
pid=$!
clk=$(getconf CLK_TCK)
start=$(date +%s.%N)
: >"$out/samples.tsv"
while kill -0 "$pid" 2>/dev/null; do
    elapsed=$(echo "$(date +%s.%N) - $start" | bc)
    cpu=$(awk -v c="$clk" '{print ($14 + $15) / c}' "/proc/$pid/stat" 2>/dev/null || true)
    metrics=$(ls "$out"/*/metrics.jsonl 2>/dev/null | head -1 || true)
    updates=$([ -n "$metrics" ] && tail -1 "$metrics" | grep -o '"updates":[0-9]*' | cut -d: -f2 || true)
    [ -n "$cpu" ] && printf '%s\t%s\t%s\n' "$elapsed" "$cpu" "${updates:-0}" >>"$out/samples.tsv"
    if (($(echo "$elapsed > $t1 + 1" | bc))); then
        kill -INT "$pid"
        break
    fi
    sleep 2
done
wait "$pid" || true
python3 - "$out/samples.tsv" "$t0" "$t1" "$name" <<'PY'
import sys
rows = [tuple(map(float, l.split("\t"))) for l in open(sys.argv[1]) if l.strip()]
t0, t1, name = float(sys.argv[2]), float(sys.argv[3]), sys.argv[4]
a = min(rows, key=lambda r: abs(r[0] - t0))
b = min(rows, key=lambda r: abs(r[0] - t1))
inside = [r for r in rows if t0 <= r[0] <= t1]
changes = [(r[0], r[2]) for i, r in enumerate(inside) if i == 0 or r[2] != inside[i - 1][2]]
first, last = (changes[1] if len(changes) > 2 else changes[0]), changes[-1]
rate = (last[1] - first[1]) / (last[0] - first[0]) if last[0] > first[0] else float("nan")
print(f"{name}: {a[0]:.0f}-{b[0]:.0f} s: cores busy {(b[1] - a[1]) / (b[0] - a[0]):.2f}; "
      f"updates/s {rate:.3f} ({first[1]:.0f} updates at {first[0]:.0f} s -> {last[1]:.0f} at {last[0]:.0f} s)")
PY
