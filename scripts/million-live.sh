#!/usr/bin/env bash
# A million-object live world (issue 25's goal): `myriad cluster --live` with K zone
# processes (default 4; scenario 3's map, its 99,999 statics and 10,000 users, with
# 1,000,000 dynamic objects in all: `--scenario custom` on the map of reference scenario
# MAP, which the gateways build; on cuda with every zone on GPU 0; 30 ticks a second), G gateways started by the cluster (default 2) and N bots on
# each (default 100, shuttling back and forth along x across the cuts) for D seconds.
# Prints what the bots saw (logins, reconnects, own object seen, moves), each zone's
# tick, step and fabric bytes, each gateway's bytes in from the zones and out to its
# players and its player hand-offs between zones, and every process's memory (RSS and
# peak); the raw metrics, logs and bots' JSON stay in OUT_DIR.
#
# Usage: scripts/million-live.sh [-b BINARY] [-x BACKEND] [-n DYNAMIC] [-s MAP] [-k ZONES] [-g GATEWAYS] [-p BOTS_PER_GATEWAY] [-d SECONDS] [-o OUT_DIR]
# Needs NATS at 127.0.0.1:4222 (or NATS_URL).
set -euo pipefail
BIN=target/release/myriad; BACKEND=cuda; DYN=1000000; SC=3; K=4; G=2; P=100; D=60; OUTDIR=""
while getopts "b:x:n:s:k:g:p:d:o:" o; do case $o in
  b) BIN=$OPTARG;; x) BACKEND=$OPTARG;; n) DYN=$OPTARG;; s) SC=$OPTARG;; k) K=$OPTARG;; g) G=$OPTARG;;
  p) P=$OPTARG;; d) D=$OPTARG;; o) OUTDIR=$OPTARG;;
  *) sed -n 2,12p "$0"; exit 2;; esac; done
# The statics and users of reference scenario MAP (its map: size 1024, the default).
case $SC in
  1) MAP=(--static 3000 --users 1000);; 2) MAP=(--static 15000 --users 5000);; 3) MAP=(--static 99999 --users 10000);;
  *) echo "-s: a reference scenario's map, 1, 2 or 3" >&2; exit 2;; esac
URL=${NATS_URL:-nats://127.0.0.1:4222}
MYRIAD_CLUSTER_KEY=$(head -c 24 /dev/urandom | od -An -tx1 | tr -d ' \n')
export MYRIAD_CLUSTER_KEY
DIR=${OUTDIR:-$(mktemp -d)}; mkdir -p "$DIR"
PORT=$((20000 + RANDOM % 20000)); MPORT=$((PORT + 1000))
pids=()
cleanup() { for p in "${pids[@]}"; do kill "$p" 2>/dev/null || true; done; }
trap cleanup EXIT
for g in $(seq 0 $((G - 1))); do
  "$BIN" user seed --count $((G * P)) --data-dir "$DIR/gw/gateway-$g" >/dev/null
done
START=$(date +%s)
# A checkpoint every 10 s: each zone's is tens of MB at this size, written on its tick.
"$BIN" cluster --nats "$URL" --cluster "ml$$" --zones "$K" --gpus 1 --live --tick-hz 30 --ticks 10000000 \
  --checkpoint-every 300 \
  --scenario custom "${MAP[@]}" --dynamic "$DYN" --seed 1 --backend "$BACKEND" --gateways "$G" --gateway-port "$PORT" \
  --gateway-data "$DIR/gw" --metrics-base-port "$MPORT" >"$DIR/cluster.out" 2>"$DIR/cluster.log" &
pids+=($!)
# A metric's value (summed over its labels) from the endpoint on port $1; 0 when down.
# Plain bash, no curl: the lent GPU machine may have none.
m() {
  local page=""
  if exec 3<>"/dev/tcp/127.0.0.1/$1" 2>/dev/null; then
    printf 'GET /metrics HTTP/1.0\r\nHost: x\r\n\r\n' >&3
    page=$(cat <&3)
    exec 3>&-
  fi
  awk -v n="$2" '$1 == n || index($1, n "{") == 1 {s += $2} END {print s + 0}' <<<"$page"
}
# Ready: every gateway's login answers and has taken worlds from the zones.
for _ in $(seq 1 240); do
  ready=1
  for g in $(seq 0 $((G - 1))); do
    (( $(m $((MPORT + 100 + g)) myriad_gateway_mirrors_total) > 30 )) || ready=0
  done
  [ "$ready" = 1 ] && break
  sleep 1
done
if [ "$ready" = 0 ]; then echo "the gateways took no worlds in 240 s" >&2; tail -5 "$DIR/cluster.log" >&2; exit 1; fi
echo "cluster ready after $(( $(date +%s) - START )) s"
bots=()
for g in $(seq 0 $((G - 1))); do
  "$BIN" bots --server 127.0.0.1:$((PORT + 2 * g + 1)) --cert "$DIR/gw/gateway-$g/tls-cert.pem" --count "$P" \
    --first $((g * P)) --behaviour shuttle --duration "$D" --json >"$DIR/bots$g.json" 2>"$DIR/bots$g.log" &
  bots+=($!); pids+=($!)
done
snap() {
  for z in $(seq 0 $((K - 1))); do
    for n in myriad_zone_ticks_total myriad_zone_step_seconds_total myriad_zone_physics_seconds_total \
      myriad_zone_wait_seconds_total myriad_zone_publish_seconds_total myriad_zone_fabric_sent_bytes_total \
      myriad_zone_owned_objects; do
      echo "zone $z $n $(m $((MPORT + z)) "$n")"; done; done
  for g in $(seq 0 $((G - 1))); do
    for n in myriad_gateway_mirrors_total myriad_gateway_zone_bytes_in_total myriad_bytes_sent_total \
      myriad_gateway_player_handoffs_total myriad_gateway_subscription_cells myriad_gateway_rollbacks_total \
      myriad_gateway_zone_objects_in_total myriad_gateway_zone_nudges_in_total myriad_gateway_held_objects \
      myriad_gateway_resyncs_total myriad_gateway_skipped_ticks_total; do
      echo "gateway $g $n $(m $((MPORT + 100 + g)) "$n")"; done; done
}
sleep 10; snap >"$DIR/a"; T0=$(date +%s.%N)
sleep $((D / 2 - 10))
# Memory mid-run, of every process the cluster started.
grep -oE '(zone|gateway) [0-9]+ pid [0-9]+' "$DIR/cluster.log" | while read -r what i _ pid; do
  echo "$what $i $(awk '/VmRSS|VmHWM/ {printf "%s %d MB ", $1, $2 / 1024}' "/proc/$pid/status" 2>/dev/null)"
done >"$DIR/memory.txt"
for b in "${bots[@]}"; do wait "$b" || true; done
snap >"$DIR/b"; T1=$(date +%s.%N)
python3 - "$DIR" "$T0" "$T1" "$G" <<'PY'
import json, sys
d, t0, t1, g = sys.argv[1], float(sys.argv[2]), float(sys.argv[3]), int(sys.argv[4])
def load(p):
    out = {}
    for l in open(p):
        what, i, name, v = l.split()
        out[(what, int(i), name)] = float(v)
    return out
a, b = load(f"{d}/a"), load(f"{d}/b")
dt = t1 - t0
delta = lambda k: b[k] - a[k]
zones = sorted({i for (w, i, _) in b if w == "zone"})
print(f"measured window {dt:.1f} s")
for z in zones:
    t = delta(("zone", z, "myriad_zone_ticks_total")) or 1
    print(f"zone {z}: {t / dt:.1f} ticks/s, step {1e3 * delta(('zone', z, 'myriad_zone_step_seconds_total')) / t:.2f} ms"
          f" (physics {1e3 * delta(('zone', z, 'myriad_zone_physics_seconds_total')) / t:.2f}),"
          f" wait {1e3 * delta(('zone', z, 'myriad_zone_wait_seconds_total')) / t:.2f} ms,"
          f" publish {1e3 * delta(('zone', z, 'myriad_zone_publish_seconds_total')) / t:.2f} ms a tick,"
          f" fabric out {delta(('zone', z, 'myriad_zone_fabric_sent_bytes_total')) / dt / 1e6:.2f} MB/s,"
          f" owns {b[('zone', z, 'myriad_zone_owned_objects')]:.0f}")
for i in range(g):
    k = lambda n: ("gateway", i, n)
    bin_, bout = delta(k("myriad_gateway_zone_bytes_in_total")), delta(k("myriad_bytes_sent_total"))
    print(f"gateway {i}: {delta(k('myriad_gateway_mirrors_total')) / dt:.1f} worlds/s, in from zones {bin_ / dt / 1e6:.2f} MB/s,"
          f" out to players {bout / dt / 1e6:.2f} MB/s (in/out {bin_ / max(bout, 1):.2f}),"
          f" {delta(k('myriad_gateway_player_handoffs_total')):.0f} player hand-offs,"
          f" {b[k('myriad_gateway_subscription_cells')]:.0f} cells, {b[k('myriad_gateway_rollbacks_total')]:.0f} rollbacks,"
          f" holds {b[k('myriad_gateway_held_objects')]:.0f} objects, records in {delta(k('myriad_gateway_zone_objects_in_total')) / dt:.0f}/s"
          f" ({delta(k('myriad_gateway_zone_nudges_in_total')) / dt:.0f} nudges),"
          f" {delta(k('myriad_gateway_resyncs_total')):.0f} resyncs, {delta(k('myriad_gateway_skipped_ticks_total')):.0f} zone ticks skipped")
for i in range(g):
    final = [json.loads(l) for l in open(f"{d}/bots{i}.json") if '"final"' in l]
    print(f"bots on gateway {i}: {json.dumps(final[-1]) if final else 'no final line'}")
print(open(f"{d}/memory.txt").read().rstrip())
PY
