#!/usr/bin/env bash
# Zones with players: for each K, a live cluster of K zone processes (`myriad cluster
# --live`, cpu), one `myriad gateway` and N bots for D seconds, all on this machine;
# prints per K the gateway's tick (median of its 1 s windows), how often it found no new
# world, the zones' step, physics and wait per tick, ghost records and fabric bytes per
# tick, and what the bots saw.
#
# Usage: scripts/zones-bots.sh [-b BINARY] [-k "1 2 4"] [-n BOTS] [-d SECONDS] [-s SCENARIO]
# Needs NATS at 127.0.0.1:4222 (or NATS_URL).
set -euo pipefail
BIN=target/release/myriad; KS="1 2 4"; BOTS=100; DUR=30; SC=1
while getopts "b:k:n:d:s:" o; do case $o in
  b) BIN=$OPTARG;; k) KS=$OPTARG;; n) BOTS=$OPTARG;; d) DUR=$OPTARG;; s) SC=$OPTARG;;
  *) sed -n 2,10p "$0"; exit 2;; esac; done
URL=${NATS_URL:-nats://127.0.0.1:4222}
MYRIAD_CLUSTER_KEY=$(head -c 24 /dev/urandom | od -An -tx1 | tr -d ' \n')
export MYRIAD_CLUSTER_KEY
DIR=$(mktemp -d); trap 'kill $(jobs -p) 2>/dev/null || true; rm -rf "$DIR"' EXIT
"$BIN" user seed --count "$BOTS" --data-dir "$DIR/d" >/dev/null
m() { curl -s "http://127.0.0.1:$1/metrics" | awk -v n="$2" '$1 == n || index($1, n "{") == 1 {s += $2} END {print s + 0}'; }
for K in $KS; do
  P=$((20000 + RANDOM % 20000)); C="zb$$k$K"
  "$BIN" cluster --nats "$URL" --cluster "$C" --zones "$K" --live --scenario "$SC" --seed 1 --backend cpu \
    --tick-hz 30 --ticks 100000 --metrics-base-port "$P" >"$DIR/cluster$K.log" 2>&1 & CL=$!
  "$BIN" gateway --nats "$URL" --cluster "$C" --zones "$K" --scenario "$SC" --seed 1 --backend cpu \
    --data-dir "$DIR/d" --udp 127.0.0.1:$((P+100)) --login 127.0.0.1:$((P+101)) --metrics 127.0.0.1:$((P+102)) \
    --set log_stages_every_s=1 >"$DIR/gw$K.log" 2>&1 & GW=$!
  for _ in $(seq 1 120); do (( $(m $((P+102)) myriad_gateway_mirrors_total) > 30 )) && break; sleep 0.5; done
  "$BIN" bots --server 127.0.0.1:$((P+101)) --cert "$DIR/d/tls-cert.pem" --count "$BOTS" --duration 5 >/dev/null 2>&1
  # The measured window: metrics before and after D seconds of bots.
  snap() { for z in $(seq 0 $((K-1))); do for n in myriad_zone_ticks_total myriad_zone_step_seconds_total \
    myriad_zone_physics_seconds_total myriad_zone_wait_seconds_total myriad_zone_ghosts_out_total \
    myriad_zone_fabric_sent_bytes_total; do echo "$z $n $(m $((P+z)) $n)"; done; done; }
  snap >"$DIR/a"; S0=$(m $((P+102)) myriad_gateway_stale_steps_total); T0=$(m $((P+102)) myriad_gateway_mirrors_total)
  "$BIN" bots --server 127.0.0.1:$((P+101)) --cert "$DIR/d/tls-cert.pem" --count "$BOTS" --duration "$DUR" >"$DIR/bots$K.log" 2>&1
  snap >"$DIR/b"; S1=$(m $((P+102)) myriad_gateway_stale_steps_total); T1=$(m $((P+102)) myriad_gateway_mirrors_total)
  python3 - "$K" "$DIR/a" "$DIR/b" "$DIR/gw$K.log" "$((S1-S0))" "$((T1-T0))" <<'PY'
import sys, re, statistics
k = int(sys.argv[1])
def load(p):
    d = {}
    for l in open(p):
        z, n, v = l.split(); d[(int(z), n)] = float(v)
    return d
a, b = load(sys.argv[2]), load(sys.argv[3])
delta = lambda z, n: b[(z, n)] - a[(z, n)]
ticks = [delta(z, 'myriad_zone_ticks_total') for z in range(k)]
per = lambda n, scale=1.0: [delta(z, n) / max(ticks[z], 1) * scale for z in range(k)]
ticks_ms = [float(m.group(1)) for m in re.finditer(r'tick ([0-9.]+) ms \(max', open(sys.argv[4]).read())][-30:]
fmt = lambda xs: '/'.join(f'{x:.2f}' for x in xs)
print(f"K={k}: gateway tick median {statistics.median(ticks_ms):.2f} ms over {len(ticks_ms)} windows, "
      f"{sys.argv[5]} stale of {int(sys.argv[6])} worlds; per zone and tick: step {fmt(per('myriad_zone_step_seconds_total', 1e3))} ms, "
      f"physics {fmt(per('myriad_zone_physics_seconds_total', 1e3))} ms, wait {fmt(per('myriad_zone_wait_seconds_total', 1e3))} ms, "
      f"ghost records {fmt(per('myriad_zone_ghosts_out_total'))}, fabric {fmt(per('myriad_zone_fabric_sent_bytes_total', 1e-3))} kB")
PY
  echo "  bots: $(tail -1 "$DIR/bots$K.log" | cut -d'|' -f2-)"
  kill $GW $CL 2>/dev/null; wait $GW $CL 2>/dev/null || true
done
