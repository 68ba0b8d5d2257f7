#!/usr/bin/env bash
# What a player gets through a real (lossy) link, here, on loopback: a fresh `myriad serve`
# (scenario 2's map, the default NPCs and AOI, `cpu`), 100 `myriad bots` for DURATION
# seconds straight to it, then through `myriad relay` with 5 % loss each way, 100 ± 20 ms
# and 1 % reordering. The bots' last JSON line of each run (kB/s, updates, staleness,
# decode errors, reconnects) goes to OUT_DIR/relay-{clean,lossy}.json.
#
# Usage: scripts/relay-figures.sh MYRIAD_BINARY OUT_DIR
#        (DURATION=30 BOTS=100 LOSS=0.05 DELAY_MS=100 JITTER_MS=20 REORDER=0.01)
set -euo pipefail
bin=$(realpath "$1")
out=$(realpath -m "$2")
mkdir -p "$out"
duration=${DURATION:-30}
bots=${BOTS:-100}
data=$(mktemp -d)
trap 'kill $(jobs -p) 2>/dev/null || true; rm -rf "$data"' EXIT
# A port range unlikely to be in use; the server's UDP on 127.0.0.2, where the relay
# forwards, and the relay on 127.0.0.1, where the login's answer sends the bots.
login=127.0.0.1:17878
udp_port=17877

"$bin" user seed --count "$bots" --data-dir "$data" >/dev/null
"$bin" serve --data-dir "$data" --scenario 2 --login "$login" --udp "127.0.0.2:$udp_port" \
    --admin 127.0.0.1:17880 >"$out/serve.log" 2>&1 &
for _ in $(seq 1 120); do
    grep -q "tick loop ready" "$out/serve.log" && break
    sleep 0.5
done

run() { # name, then the relay's impairments (none: a relay that forwards everything
    # untouched, the clean link: the bots reach the server's UDP only through a relay)
    local name=$1
    shift
    "$bin" relay --listen "127.0.0.1:$udp_port" --server "127.0.0.2:$udp_port" --seed 7 \
        --duration "$((duration + 30))" "$@" >"$out/relay-$name.log" 2>&1 &
    local relay=$!
    sleep 0.5
    "$bin" bots --server "$login" --count "$bots" --duration "$duration" --cert "$data/tls-cert.pem" --json \
        >"$out/bots-$name.jsonl" 2>"$out/bots-$name.err" || echo "bots ($name) failed" >&2
    tail -n 1 "$out/bots-$name.jsonl" >"$out/relay-$name.json"
    kill "$relay" 2>/dev/null || true
    wait "$relay" 2>/dev/null || true
}

run clean
run lossy --loss "${LOSS:-0.05}" --delay-ms "${DELAY_MS:-100}" --jitter-ms "${JITTER_MS:-20}" \
    --reorder "${REORDER:-0.01}"
for name in clean lossy; do
    echo "== $name"
    cat "$out/relay-$name.json"
done
