#!/usr/bin/env bash
# Live rebalancing, measured: the moving crowd in a live cluster of K zone processes
# (`myriad cluster`, one process a zone, at 30 ticks a second), once with fixed cuts and
# once with `--rebalance` (the supervisor's step-time policy). From the zones' loads the
# supervisor saw in their heartbeats (`load_samples` of `--json`), prints per run how
# far the slowest zone's step is over the mean: before the crowd reaches the middle of
# the map, in the 10 s after (the issue's goal: at most 1.3 x), and after; the same for
# owned objects; the cut moves; and whether both runs ended in `myriad sim`'s hash.
#
# Usage: scripts/rebalance-live.sh [-b BINARY] [-k ZONES] [-t TICKS] [-u USERS] [-a ARRIVAL_TICK] [-o OUT_DIR] [-x BACKEND]
# Needs NATS at 127.0.0.1:4222 (or NATS_URL). Zones want cores of their own: on a
# machine with few cores the step times are mostly the other processes'.
set -euo pipefail
BIN=target/release/myriad; K=4; TICKS=2000; USERS=3000; ARRIVAL=1155; OUTDIR=""; BACKEND=cpu
while getopts "b:k:t:u:a:o:x:" o; do case $o in
  b) BIN=$OPTARG;; k) K=$OPTARG;; t) TICKS=$OPTARG;; u) USERS=$OPTARG;; a) ARRIVAL=$OPTARG;;
  o) OUTDIR=$OPTARG;; x) BACKEND=$OPTARG;;
  *) sed -n 2,12p "$0"; exit 2;; esac; done
URL=${NATS_URL:-nats://127.0.0.1:4222}
MYRIAD_CLUSTER_KEY=$(head -c 24 /dev/urandom | od -An -tx1 | tr -d ' \n')
export MYRIAD_CLUSTER_KEY
DIR=${OUTDIR:-$(mktemp -d)}; mkdir -p "$DIR"
WORLD=(--scenario moving-crowd --users "$USERS" --seed 1 --backend "$BACKEND" --ticks "$TICKS")
"$BIN" sim --json "${WORLD[@]}" >"$DIR/sim.json"
for MODE in fixed rebalance; do
  FLAGS=(); [ "$MODE" = rebalance ] && FLAGS=(--rebalance)
  "$BIN" cluster --json --nats "$URL" --zones "$K" --tick-hz 30 "${WORLD[@]}" "${FLAGS[@]}" \
    >"$DIR/$MODE.json" 2>"$DIR/$MODE.log"
done
python3 - "$DIR" "$ARRIVAL" <<'PY'
import json, sys, statistics
d, arrival = sys.argv[1], int(sys.argv[2])
sim = json.load(open(f"{d}/sim.json"))["state_hash"]
def ratios(samples, key, lo, hi):
    out = []
    for s in samples:
        v = s[key]
        if not (lo <= s["tick"] < hi) or any(x is None for x in v) or not v:
            continue
        mean = statistics.fmean(v)
        if mean > 0:
            out.append(max(v) / mean)
    return out
def cell(r):
    return f"{statistics.median(r):.2f} (max {max(r):.2f}, n {len(r)})" if r else "-"
print(f"moving crowd, live cluster, arrival at tick {arrival}; slowest / mean, median of the supervisor's samples")
for mode in ["fixed", "rebalance"]:
    v = json.load(open(f"{d}/{mode}.json"))
    s = v["load_samples"]
    end = v["ticks"] + 1
    print(f"== {mode}: {len(v['cut_moves'])} cut moves announced, applied at {v['cut_moves_applied']}, "
          f"faults {v['faults']}, hash {v['state_hash']} ({'equal' if v['state_hash'] == sim else 'DIFFERENT from'} sim {sim})")
    for name, lo, hi in [("before arrival", 30, arrival), ("10 s after arrival", arrival, arrival + 300),
                         ("after that", arrival + 300, end)]:
        print(f"  {name:20} step {cell(ratios(s, 'step_ms', lo, hi))}; objects {cell(ratios(s, 'owned', lo, hi))}")
    if v["cut_moves"]:
        m = v["cut_moves"][-1]
        print(f"  cuts at the end: x {m['xs'][1:-1]} z {m['zs'][1:-1]}")
PY
