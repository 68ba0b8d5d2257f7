#!/usr/bin/env bash
# kill -9 drill: `myriad serve` (SQLite in a temp dir, loopback) with N bots walking;
# samples the age of the oldest saved position every 100 ms for a while, then SIGKILLs
# the server and reports how old the newest and the oldest saved rows were at the kill.
#
# Usage: scripts/kill-drill.sh [-b BINARY] [-n BOTS] [-d SECONDS_BEFORE_KILL] [-r ROUNDS]
set -euo pipefail
BIN=target/release/myriad; BOTS=100; DUR=8; ROUNDS=3
while getopts "b:n:d:r:" o; do case $o in
  b) BIN=$OPTARG;; n) BOTS=$OPTARG;; d) DUR=$OPTARG;; r) ROUNDS=$OPTARG;; *) sed -n 2,6p "$0"; exit 2;; esac; done
(( DUR <= 600 && BOTS <= 2000 && ROUNDS <= 20 )) || { echo "bounded: -d <= 600, -n <= 2000, -r <= 20" >&2; exit 2; }
DIR=$(mktemp -d); SRV=""; BOTSPID=""
trap 'kill -9 $SRV $BOTSPID 2>/dev/null || true; rm -rf "$DIR"' EXIT
"$BIN" user seed --count "$BOTS" --data-dir "$DIR" --set hash_memory_kib=1024 --set hash_passes=1 >/dev/null
ms() { date +%s%3N; }
q() { sqlite3 -cmd ".timeout 2000" "$DIR/myriad.db" "$1"; }
for round in $(seq 1 "$ROUNDS"); do
  P=$((20000 + RANDOM % 20000))
  "$BIN" serve --data-dir "$DIR" --udp 127.0.0.1:$P --login 127.0.0.1:$((P+1)) --backend cpu >"$DIR/serve.log" 2>&1 & SRV=$!
  for _ in $(seq 1 120); do grep -q "server started" "$DIR/serve.log" && break; sleep 0.5; done
  "$BIN" bots --server 127.0.0.1:$((P+1)) --cert "$DIR/tls-cert.pem" --count "$BOTS" --duration 600 \
    --behaviour circle >/dev/null 2>&1 & BOTSPID=$!
  for _ in $(seq 1 600); do [[ $(q "select count(*) from player_state") -ge $BOTS ]] && break; sleep 0.1; done
  sleep 1
  WORST=0; END=$(( $(ms) + DUR * 1000 ))
  while (( $(ms) < END )); do
    NOW=$(ms); OLDEST=$(q "select min(updated_at) from player_state")
    (( NOW - OLDEST > WORST )) && WORST=$((NOW - OLDEST))
    sleep 0.1
  done
  KILLED=$(ms); kill -9 $SRV; wait $SRV 2>/dev/null || true
  read -r NEWEST OLDEST <<<"$(q "select max(updated_at), min(updated_at) from player_state" | tr '|' ' ')"
  echo "round $round: at the kill the newest saved row was $((KILLED - NEWEST)) ms old, the oldest $((KILLED - OLDEST)) ms; sampled every 100 ms while playing: up to $WORST ms"
  kill $BOTSPID 2>/dev/null || true; wait $BOTSPID 2>/dev/null || true
done
