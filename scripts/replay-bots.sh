#!/usr/bin/env bash
# A live run replayed bit for bit (issue 24's goal), on this machine: `myriad cluster
# --live` with 2 zones (scenario 1, cpu, 30 ticks a second), a gateway and N bots walking
# back and forth across the cut for D seconds; zone 1 is killed (kill -9) a third of the
# way through, the cluster rolls back and ends at its last tick; then `myriad replay`
# re-runs the world from the rollback's checkpoint with the intents the zones logged
# and must end in the hash the live zones stored. Prints the bots' final line, the
# cluster's summary and the replay's; exits non-zero when the replay differs.
#
# Usage: scripts/replay-bots.sh [-b path/to/myriad] [-n bots] [-d seconds]
# Needs NATS at 127.0.0.1:4222 (as `myriad cluster` without --nats).
set -euo pipefail
bin=target/release/myriad
n=100
d=60
while getopts b:n:d: o; do
    case $o in
    b) bin=$OPTARG ;;
    n) n=$OPTARG ;;
    d) d=$OPTARG ;;
    *) exit 2 ;;
    esac
done
work=$(mktemp -d)
pids=()
cleanup() {
    for p in "${pids[@]}"; do kill "$p" 2>/dev/null || true; done
    rm -rf "$work"
}
trap cleanup EXIT
MYRIAD_CLUSTER_KEY=$(head -c 24 /dev/urandom | od -An -tx1 | tr -d ' \n')
export MYRIAD_CLUSTER_KEY
name="rp$$"
ticks=$(((d + 25) * 30))
common=(--zones 2 --scenario 1 --backend cpu --checkpoint-every 30 --ticks "$ticks")
common+=(--keep-checkpoints "$((ticks / 30 + 2))")
"$bin" user seed --count "$n" --data-dir "$work/gw" >/dev/null
"$bin" cluster --cluster "$name" --live --tick-hz 30 "${common[@]}" --json >"$work/cluster.json" 2>"$work/cluster.log" &
cluster=$!
pids+=("$cluster")
"$bin" gateway --cluster "$name" --zones 2 --scenario 1 --backend cpu --data-dir "$work/gw" \
    --login 127.0.0.1:7601 --udp 127.0.0.1:7600 --metrics 127.0.0.1:7602 >/dev/null 2>"$work/gateway.log" &
pids+=($!)
for _ in $(seq 1 100); do
    [[ -s $work/gw/tls-cert.pem ]] && (: </dev/tcp/127.0.0.1/7601) 2>/dev/null && break
    sleep 0.3
done
"$bin" bots --server 127.0.0.1:7601 --cert "$work/gw/tls-cert.pem" --count "$n" --behaviour shuttle \
    --duration "$d" --json >"$work/bots.json" 2>/dev/null &
bots=$!
pids+=("$bots")
sleep $((d / 3))
zone1=$(grep -m1 -o 'zone 1 pid [0-9]*' "$work/cluster.log" | awk '{print $4}')
echo "killing zone 1 (pid $zone1) at $(date -u +%T)"
kill -9 "$zone1"
wait "$bots" || true
echo "bots: $(grep '"final"' "$work/bots.json" | tail -1)"
# Players' objects that changed zone under their sessions, as the gateway saw them.
curl -s http://127.0.0.1:7602/metrics | grep -E '^myriad_gateway_(player_handoffs|rollbacks|duplicates)_total' || true
wait "$cluster"
echo "cluster: $(cat "$work/cluster.json")"
grep -E '^(fault|epoch [0-9]+ +from)' "$work/cluster.log" || true
"$bin" replay --cluster "$name" "${common[@]}" --json
