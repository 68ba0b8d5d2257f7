#!/usr/bin/env bash
# Database outage drill against MariaDB at 127.0.0.1:3306 (user myriad/myriad, as CI
# sets up), through scripts/db-proxy.py so the shared server itself is never stopped:
# 50 bots walk; the database is refused for 8 s and comes back, stalls for 8 s and comes
# back, then stalls again and the server gets SIGTERM. Prints the server's log lines about
# the database, how long shutdown took and its exit status.
#
# Usage: scripts/db-drill.sh [-b BINARY] [SERVE FLAGS...]   (CI's .ci/run creates the user)
set -euo pipefail
BIN=target/release/myriad
[[ ${1:-} == -b ]] && { BIN=$2; shift 2; }
SRV=""; BOTSPID=""; DB=myriad_drill_$$; DIR=$(mktemp -d); P=$((20000 + RANDOM % 20000)); PROXY=$((P + 5))
mariadb -uroot -h127.0.0.1 -e "CREATE DATABASE $DB"
trap 'kill $SRV $BOTSPID $PX 2>/dev/null || true; mariadb -uroot -h127.0.0.1 -e "DROP DATABASE IF EXISTS $DB"; rm -rf "$DIR"' EXIT
python3 "$(dirname "$0")/db-proxy.py" $PROXY 3306 >"$DIR/proxy.log" 2>&1 & PX=$!
"$BIN" user seed --count 50 --database-url "mysql://myriad:myriad@127.0.0.1:3306/$DB" --data-dir "$DIR" \
  --set hash_memory_kib=1024 --set hash_passes=1 >/dev/null
sleep 0.5
"$BIN" serve --data-dir "$DIR" --database-url "mysql://myriad:myriad@127.0.0.1:$PROXY/$DB" \
  --udp 127.0.0.1:$P --login 127.0.0.1:$((P+1)) --backend cpu --set log_stages_every_s=0 "$@" >"$DIR/serve.log" 2>&1 & SRV=$!
for _ in $(seq 1 120); do grep -q "server started" "$DIR/serve.log" && break; sleep 0.5; done
"$BIN" bots --server 127.0.0.1:$((P+1)) --cert "$DIR/tls-cert.pem" --count 50 --duration 120 >/dev/null 2>&1 & BOTSPID=$!
sleep 6
echo "== refused for 8 s";  kill -USR2 $PX; sleep 8; kill -USR2 $PX; sleep 8
echo "== stalled for 8 s";  kill -USR1 $PX; sleep 8; kill -USR1 $PX; sleep 8
echo "== stalled, then SIGTERM"; kill -USR1 $PX; sleep 3
T0=$(date +%s%3N); kill -TERM $SRV; set +e; wait $SRV; RC=$?; set -e; T1=$(date +%s%3N)
echo "shutdown took $((T1 - T0)) ms, exit status $RC"
[[ -n ${KEEP_LOG:-} ]] && cp "$DIR/serve.log" "$KEEP_LOG"
grep -iE "database|position|store|stopped|error|panicked|lost|saved" "$DIR/serve.log" | grep -v "login ok" | sed 's/\x1b\[[0-9;]*m//g' | cut -c1-400
