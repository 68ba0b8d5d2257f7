#!/usr/bin/env bash
# Soak / login-burst drill: starts `myriad serve` (SQLite in a temp dir, loopback only),
# seeds accounts at the default password-hash cost, runs `myriad bots` for a bounded
# time, and samples the server's resident memory (VmRSS) and its tick metrics.
#
# Usage: scripts/soak.sh [-b BINARY] [-n BOTS] [-d SECONDS] [-c LOGINS_IN_FLIGHT] [-s SAMPLE_S]
#   -b  the myriad binary (default: target/release/myriad)
#   -n  bots (default 300)         -d  seconds the bots play (default 60)
#   -c  logins in flight (default 32; 1000 with -n 1000 is a login burst)
#   -s  seconds between RSS samples (default 5)
#   -m  stop the drill if the server's RSS passes this many MiB (default 6000), so a
#       leaking build cannot take the machine down
# Prints: RSS of the fresh server (world built, nobody logged in), after the logins, peak
# and at the end; tick percentiles from the `myriad_tick_duration_seconds` histogram
# (bucket upper bounds) over the bots' run; ticks over 50 ms and 100 ms; and, when the
# binary exports it, `myriad_slow_ticks_total` (ticks over twice the dilated period).
# KEEP_LOG=FILE keeps the server's log; SERVE_ARGS="--set k=v ..." adds server flags.
set -euo pipefail
BIN=target/release/myriad; BOTS=300; DUR=60; CONC=32; SAMPLE=5; MAXMIB=6000
while getopts "b:n:d:c:s:m:" o; do case $o in
  b) BIN=$OPTARG;; n) BOTS=$OPTARG;; d) DUR=$OPTARG;; c) CONC=$OPTARG;; s) SAMPLE=$OPTARG;; m) MAXMIB=$OPTARG;;
  *) sed -n 2,14p "$0"; exit 2;; esac; done
(( DUR <= 3600 && BOTS <= 10000 )) || { echo "bounded: at most 3600 s and 10000 bots" >&2; exit 2; }
# SERVE_ARGS is a list of flags: split it on whitespace, once.
read -ra serve_args <<<"${SERVE_ARGS:-}"
DIR=$(mktemp -d); trap 'kill $SRV 2>/dev/null || true; rm -rf "$DIR"' EXIT
P=$((20000 + RANDOM % 20000))
UDP=127.0.0.1:$P LOGIN=127.0.0.1:$((P+1)) MET=127.0.0.1:$((P+2))
"$BIN" user seed --count "$BOTS" --data-dir "$DIR" >/dev/null
"$BIN" serve --data-dir "$DIR" --udp $UDP --login $LOGIN --metrics $MET --backend cpu \
  --set log_stages_every_s=1 "${serve_args[@]}" >"$DIR/serve.log" 2>&1 & SRV=$!
for _ in $(seq 1 120); do grep -q "server started" "$DIR/serve.log" && break; sleep 0.5; done
rss() { awk '/VmRSS/ {print int($2/1024)}' /proc/$SRV/status; }
metrics() { curl -s "http://$MET/metrics"; }
sleep 3; FRESH=$(rss); metrics >"$DIR/m0"
"$BIN" bots --server $LOGIN --cert "$DIR/tls-cert.pem" --count "$BOTS" --duration "$DUR" \
  --login-concurrency "$CONC" --every 5 >"$DIR/bots.log" 2>&1 & BOTSPID=$!
PEAK=$FRESH; AFTER_LOGIN=""; T0=$(date +%s)
while kill -0 $BOTSPID 2>/dev/null; do
  R=$(rss); (( R > PEAK )) && PEAK=$R
  if (( R > MAXMIB )); then echo "RSS ${R} MiB over the -m limit ${MAXMIB}: stopping"; kill $BOTSPID; break; fi
  if [[ -z $AFTER_LOGIN ]] && grep -q "^logins: " "$DIR/bots.log" 2>/dev/null; then AFTER_LOGIN=$R; fi
  SLOW=$(metrics | awk '/^myriad_slow_ticks_total/ {print $2}')
  PLAYERS=$(metrics | awk '/^myriad_players / {print $2}')
  echo "t=$(( $(date +%s) - T0 ))s rss=${R}MiB players=${PLAYERS:-?} slow_ticks=${SLOW:-0}"
  sleep "$SAMPLE"
done
wait $BOTSPID 2>/dev/null || true
metrics >"$DIR/m1"; END=$(rss)
python3 - "$DIR/m0" "$DIR/m1" <<'PY'
import sys, re
def load(p):
    b, c, slow = {}, 0, None
    for l in open(p):
        m = re.match(r'myriad_tick_duration_seconds_bucket\{le="([^"]+)"\} (\S+)', l)
        if m: b[m.group(1)] = float(m.group(2))
        if l.startswith('myriad_tick_duration_seconds_count'): c = float(l.split()[1])
        if l.startswith('myriad_slow_ticks_total'): slow = float(l.split()[1])
    return b, c, slow
(b0, c0, s0), (b1, c1, s1) = load(sys.argv[1]), load(sys.argv[2])
n = c1 - c0
les = sorted((float(k) if k != '+Inf' else float('inf'), k) for k in b1)
d = [(v, b1[k] - b0.get(k, 0)) for v, k in les]
def pct(q):
    for v, cum in d:
        if cum >= q * n: return v
print(f"ticks {int(n)}; tick p50 <= {pct(.5)*1000:g} ms, p99 <= {pct(.99)*1000:g} ms, p99.9 <= {pct(.999)*1000:g} ms, max bucket <= {max(v for v,c in d if c < n) if any(c < n for v,c in d) else 0}")
over = lambda le: int(n - dict(d).get(le, n))
print(f"ticks over 50 ms: {over(0.05)}, over 100 ms: {over(0.1)}, over 1 s: {over(1.0)}")
if s1 is not None: print(f"ticks over twice the dilated period (myriad_slow_ticks_total): {int(s1 - (s0 or 0))}")
PY
echo "dilation seen: $(grep -o 'dilation [0-9]*' "$DIR/serve.log" | sort -u | tr '\n' ' ')"
echo "max tick per 1 s window (ms): $(grep -o 'max [0-9.]*' "$DIR/serve.log" | awk '{print $2}' | sort -n | tail -3 | tr '\n' ' ')"
echo "the window with the longest tick:"
grep 'myriad::stages' "$DIR/serve.log" | sed 's/.*myriad::stages[^ ]* //' | awk -F'max ' '{split($2, a, ")"); print a[1] "\t" $0}' | sort -n | tail -1 | cut -f2-
[[ -n ${KEEP_LOG:-} ]] && cp "$DIR/serve.log" "$KEEP_LOG"
tail -2 "$DIR/bots.log"
echo "RSS MiB: fresh $FRESH, after $BOTS logins ${AFTER_LOGIN:-?}, peak $PEAK, end $END"
