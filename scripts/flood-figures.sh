#!/usr/bin/env bash
# Measures every attack of issue 14 against one `myriad` binary, on loopback:
# `myriad serve` (scenario 1's map, 5,000 NPCs, cpu backend, default password cost) with
# 50 bots playing (`myriad bots`), then `myriad flood --mode M` for each mode, with the
# server's tick figures from its metrics endpoint and a legitimate login probed from
# another address during each attack. One JSON line per attack in OUT/flood-MODE.json,
# the bots' lines in OUT/bots-MODE.jsonl.
#
#   scripts/flood-figures.sh SERVER_BINARY FLOOD_BINARY OUT_DIR [MODE...]
#
# SERVER_BINARY serves (for a "before" figure, an older build); FLOOD_BINARY must have
# `myriad flood`. SERVE_ARGS adds flags to `myriad serve` (e.g. "--set receive_thread=false").
# Mode `busy` is a control: a thread spinning on one core, sending nothing. LOGIN_VERSION=1 for a server that predates login version 2. Everything is bounded: each attack runs --duration seconds.
set -euo pipefail
server_bin=$1 flood_bin=$2 out=$3
shift 3
modes=${*:-session garbage oversized unknown-logins logins connections lockout max-seq}
duration=${DURATION:-10}
data=$(mktemp -d /tmp/myriad-flood.XXXXXX)
# SERVE_ARGS is a list of flags: split it on whitespace, once.
read -ra serve_args <<<"${SERVE_ARGS:-}"
mkdir -p "$out"
port_udp=17777 port_login=17778 port_metrics=19100

"$server_bin" user seed --count 60 --data-dir "$data" >/dev/null 2>&1

for mode in $modes; do
  "$server_bin" serve --data-dir "$data" --backend cpu --udp 127.0.0.1:$port_udp \
    --login 127.0.0.1:$port_login --metrics 127.0.0.1:$port_metrics "${serve_args[@]}" \
    >"$out/serve-$mode.log" 2>&1 &
  server=$!
  for _ in $(seq 100); do
    (exec 3<>"/dev/tcp/127.0.0.1/$port_metrics") 2>/dev/null && break
    sleep 0.2
  done
  "$flood_bin" bots --server 127.0.0.1:$port_login --cert "$data/tls-cert.pem" --count 50 \
    --duration $((duration + 12)) --every 1 --json >"$out/bots-$mode.jsonl" 2>/dev/null &
  bots=$!
  sleep 6 # the bots log in and settle
  case $mode in
    session|max-seq) who=(--user user55 --password password55 --probe-user user56 --probe-password password56) ;;
    lockout) who=(--user user57 --count 8 --probe-user user57 --probe-password password57) ;;
    logins) who=(--user user58 --probe-user user56 --probe-password password56) ;;
    *) who=(--probe-user user56 --probe-password password56) ;;
  esac
  "$flood_bin" flood --mode "$mode" --server 127.0.0.1:$port_login --udp 127.0.0.1:$port_udp \
    --cert "$data/tls-cert.pem" --metrics 127.0.0.1:$port_metrics --duration "$duration" \
    "${who[@]}" --login-version "${LOGIN_VERSION:-4}" --json >"$out/flood-$mode.json" 2>"$out/flood-$mode.err" || true
  wait $bots || true
  kill -INT $server 2>/dev/null || true
  wait $server || true
  echo "$mode: $(cat "$out/flood-$mode.json")"
done
rm -rf "$data"
