#!/usr/bin/env bash
# Runs on the lent GPU machine, in the repository root, with .carry/ built by
# scripts/gpu-build.sh: the GPU test suite (failing, not skipping, without a GPU), the
# CPU <-> GPU hash comparisons and the benchmarks. Logs go to $OUT (or ./out).
#
# MODE=tests, MODE=bench or MODE=zones runs one part; default: tests and bench. The
# zones' part checks zoned runs on cuda against one process and times scenario 3 and four
# times scenario 3 in one process and in 2 and 4 zones on the GPUs there are (one on
# nvidia-h200, two on nvidia-h200-x2), with the build in .carry/before/ interleaved when
# there is one (scripts/gpu-build.sh with BEFORE=path). MODE=flood runs issue
# 14's UDP floods (scripts/flood-figures.sh) on the host's 16 cores, where the flooder
# does not have to share the server's cores. MODE=host times the CPU backend's server
# tick (scenario 2, AOI 14 and 100) and AOI query on the host's cores, with the build in
# .carry/before/ first when there is one (scripts/gpu-build.sh with PARTS=host).
#
# MODE=zprofile splits the tick of scenario 3 in 4 zones on one GPU (see below).
# MODE=rebalance measures live rebalancing (scripts/rebalance-live.sh): the moving crowd
# in a live cluster of 4 zone processes on the host's cores, fixed cuts against the
# step-time policy, on cpu and on cuda (REBALANCE_BACKENDS, default "cpu cuda").
# MODE=million runs a million-object live world with gateways and bots
# (scripts/million-live.sh: 4 zones on the GPU, 2 gateways, 200 bots; MILLION_SECONDS,
# MILLION_RUNS: "DYNAMIC:MAP ...", default "1000000:3", or MILLION_DYNAMIC on map 3; with
# a build in .carry/before/, each run with it first).
# MODE=players times the whole server tick with bots on loopback, PLAYERS_RUNS times
# (default 2): scenario 3 (10,000 players, AOI 14 and 100, with what a player gets:
# bytes, staleness, error) and scenario 4 (50,000 players, bots grouped 20 a socket);
# PLAYERS_SCENARIOS (default "3 4") picks which, PLAYERS_AOI (default "14,100") scenario
# 4's AOI edges, PLAYERS_TIMEOUT (seconds, default none) bounds each bench run.
# MODE=replication measures what a player gets (issue 26) at 10,000 players: scenario 3
# on cuda, AOI 14 and 100, with the build in .carry/before/ first when there is one
# (scripts/gpu-build.sh with PARTS=host BEFORE=path), then this build, then this build
# with a shadow of the same budget through a simulated lossy link (5 % loss,
# 100 ± 20 ms; REPLICATION_LOSSY=0 leaves that run out), and profiled runs at AOI 100
# (per-kernel device times, before and after; REPLICATION_PROFILE=0 leaves them out,
# REPLICATION_PROFILE_AOI="14 100" profiles each edge listed, REPLICATION_PROFILE_BEFORE=0
# profiles this build only); REPLICATION_S2=1 adds scenario 2 (5,000 players) at AOI 100,
# before and after; REPLICATION_S4=1 scenario 4 (50,000 players, bots 20 a socket) at AOI
# 14, before and after (REPLICATION_S4_TIMEOUT seconds at most each; profiled with
# REPLICATION_S4_PROFILE=1; REPLICATION_S4_AOI=100 at another edge). REPLICATION_S3=0
# leaves out scenario 3 (for a second run of the others in the same call);
# REPLICATION_AOI (default "14,100") picks scenario 3's AOI edges, and
# REPLICATION_TIMEOUT (seconds, default none) bounds each of its runs, before, after and
# lossy alike, so that one slow run leaves the call time for the others (its log
# says, every 10 ticks, where the run's time went).
#
# MODE=table measures issue 27's table, step by step (TABLE_STEPS, in order; default
# "physics s4-14 s2-100 profile-s4-14 profile-s4-100 profile-s2-100 profile-physics
# s4-100 zones"), each step TABLE_ROUNDS times (default 2), alternating the build in
# .carry/before/ (when there is one) with this one round by round: physics (scenario 3's
# and 2 M + 1 M objects' steps), s4-14 and s4-100 (scenario 4, 50,000 players, bots 20 a
# socket, AOI 14 or 100; s4: both in one run, which builds the world and the bots
# once), s3 (scenario 3's whole tick, AOI 14 and 100; s3-14 and s3-100: one of them,
# about half the time), s2-100 (scenario 2 at AOI 100),
# zones (scenario 3 in 4 zones on the GPU, once a build), refits (the physics of this
# build with MYRIAD_TREE_REFITS set to each of TABLE_REFITS, default "0 2 4 8",
# alternating round by round), chunks-X (X with this build's device outbound in chunks of
# players for each of TABLE_CHUNKS, default "1 4", alternating round by round: N sets
# MYRIAD_REPLICA_CHUNKS=N, N:TAPER also MYRIAD_REPLICA_TAPER=TAPER, as in "4:equal 4:0.6"); profile-X runs X once, this build only, with MYRIAD_CUDA_PROFILE=1. Every log lands in $OUT/table.tgz as
# soon as it is written, so a call that runs out of time still brings back the steps that
# finished. The default takes longer than one call of 600 s (scenario 4 at AOI 100 took
# over 150 s profiled on an H100): name fewer steps, or run the tests in another call.
# The device tool brings back a limited number of files: in a call that also runs
# MODE=million (dozens of files), run the table first, or its archive may be left out.
#
# Exits non-zero when any test binary or command fails or any comparison differs, and
# ends with a list of what failed (also in $OUT/failures.txt). scripts/check-gpu-run.sh
# checks that on fake bundles, without a GPU.
set -uo pipefail
out=${OUT:-out}
mkdir -p "$out"
mode=${MODE:-all}
# scripts/gpu-build.sh packs the build before (see there).
if [[ -f .carry/before/myriad.gz && ! -e .carry/before/myriad ]]; then
    gunzip .carry/before/myriad.gz
fi
export MYRIAD_REQUIRE_CUDA=1
export MYRIAD_CUBIN_CACHE=${MYRIAD_CUBIN_CACHE:-/tmp/myriad-cubin}
# Failures are appended to a file, not to a variable: most steps below run in the
# subshells of pipelines (`... | tee`), whose variables die with them.
failures="$out/failures.txt"
: >"$failures"
fail() { echo "$*" >>"$failures"; }
{
    date -u
    nvidia-smi --query-gpu=name,driver_version,memory.total,clocks.sm,clocks.mem --format=csv || true
} 2>&1 | tee "$out/device.txt"

if [[ $mode == all || $mode == tests ]]; then
    for t in .carry/tests/*; do
        echo "=== $(basename "$t")"
        "$t" --test-threads=1 --nocapture 2>&1 | grep -v '^$'
        [[ ${PIPESTATUS[0]} == 0 ]] || fail "test binary $(basename "$t") failed"
    done 2>&1 | tee "$out/tests.log"
    grep -E "^test result|^parity|FAILED|panicked" "$out/tests.log" || true
    # The CLI's own hash on the reference scenario 1, every backend.
    for b in cpu cuda-naive cuda; do
        .carry/myriad sim --scenario 1 --ticks 200 --backend "$b" --json 2>/dev/null ||
            fail "sim scenario 1 --backend $b failed"
    done | tee "$out/sim-hashes.jsonl" | python3 -c '
import json, sys
rows = [json.loads(l) for l in sys.stdin if l.strip()]
for r in rows:
    print("sim scenario 1, 200 ticks:", r["backend"], r["state_hash"], "%.3f ms a tick" % r["mean_tick_ms"])
equal = len(rows) == 3 and len({r["state_hash"] for r in rows}) == 1
print("sim hashes equal:", equal)
sys.exit(0 if equal else 1)
' || fail "sim scenario 1: the backends hashes differ (or a run is missing)"
    # Large worlds: CPU and GPU hashes after a few ticks (many sort tiles, deep trees),
    # and scenario 4's 1.3 million dynamic objects (issue 27).
    for spec in "--scenario custom --dynamic 300000 --static 150000 --users 11538 --world-size 1100.0 --ticks 30" \
        "--scenario custom --dynamic 2000000 --static 1000000 --users 76923 --world-size 2840.2 --ticks 5" \
        "--scenario 4 --ticks 5"; do
        read -r -a world <<<"$spec"
        for b in cpu cuda; do
            .carry/myriad sim "${world[@]}" --backend "$b" --json 2>/dev/null || fail "sim $spec --backend $b failed"
        done
    done | tee -a "$out/sim-hashes.jsonl" | python3 -c '
import json, sys
rows = [json.loads(l) for l in sys.stdin if l.strip()]
ok = len(rows) == 6
for a, b in zip(rows[::2], rows[1::2]):
    equal = a["dynamic"] == b["dynamic"] and a["state_hash"] == b["state_hash"]
    ok = ok and equal
    print("sim %d dynamic, %d ticks: cpu %s cuda %s equal: %s" % (a["dynamic"], a["ticks"], a["state_hash"], b["state_hash"], equal))
sys.exit(0 if ok else 1)
' || fail "sim large worlds: cpu and cuda hashes differ (or a run is missing)"
fi

if [[ $mode == all || $mode == bench ]]; then
    # Tables 1 to 3: physics on every backend, then the whole server tick (one bot per
    # user on loopback, at AOI 14 and 100) on cuda and cpu; plots into $out/bench.
    .carry/myriad bench --scenario 1,2,3 --backend cuda,cuda-naive,cpu --ticks 30 --warmup 3 --aoi-size 14,100 \
        --out "$out/bench" > "$out/bench-ref.md" 2> "$out/bench.log" || fail "bench tables 1 to 3 failed"
    sed -n '1,/#### The reference/p' "$out/bench-ref.md"
    # Scale sweep: dynamic N, static N/2, world area grows with N (density of scenario 3:
    # 260k objects on a 1024 x 1024 map).
    for n in 10000 30000 100000 300000 1000000 2000000; do
        size=$(python3 -c "import math; print(round(1024 * math.sqrt($n / 260000), 1))")
        .carry/myriad bench --scenario custom --dynamic $n --static $((n / 2)) --users $((n / 26)) \
            --world-size "$size" --backend cuda --ticks 20 --warmup 3 --format json --physics-only \
            2>> "$out/bench.log" || fail "bench sweep at $n dynamic failed"
    done > "$out/sweep.jsonl"
    # Per-kernel device times (CUDA events around every launch; slows the step a little).
    MYRIAD_CUDA_PROFILE=1 .carry/myriad bench --scenario 1,3 --backend cuda --ticks 20 --warmup 3 --physics-only \
        > /dev/null 2> "$out/profile.txt" || fail "profile of scenarios 1 and 3 failed"
    MYRIAD_CUDA_PROFILE=1 .carry/myriad bench --scenario custom --dynamic 2000000 --static 1000000 \
        --users 76923 --world-size 2840.2 --backend cuda --ticks 10 --warmup 2 --physics-only \
        > /dev/null 2>> "$out/profile.txt" || fail "profile at 2,000,000 dynamic failed"
    grep -E "per-kernel|^\|" "$out/profile.txt"
    python3 - "$out/sweep.jsonl" <<'PY'
import json, sys
print("| dynamic | static objects | total ms | build_dynamic_bvh | broad static | broad dynamic | narrow s+d | forces | upload+host | dyn pairs |")
print("| ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
for l in open(sys.argv[1]):
    if not l.strip():
        continue
    r = json.loads(l)
    print(f"| {r['dynamic']} | {r['static_objects']} | {r['total_ms']:.3f} | {r['build_dynamic_bvh']:.3f} | {r['broad_static']:.3f} | {r['broad_dynamic']:.3f} | {r['narrow_static'] + r['narrow_dynamic']:.3f} | {r['forces']:.3f} | {r['upload']:.3f} | {r['dynamic_pairs']} |")
PY
fi
if [[ $mode == zones ]]; then
    nats_pid=
    if [[ -x .carry/nats-server ]]; then
        .carry/nats-server -a 127.0.0.1 -p 4222 -js -sd /tmp/myriad-nats >/dev/null 2>&1 &
        nats_pid=$!
        sleep 1
    fi
    gpus=$(nvidia-smi -L | wc -l)
    # Every row of zones.jsonl is one `myriad sim --json`; a row without "zoned" is one
    # process and sets the hash the zoned rows after it must equal. Rows of the build in
    # .carry/before/ (if any) carry "build": "before" and are timed, not compared.
    {
        # Zoned runs on cuda equal one process on cpu: scenarios 1 and 2 and the
        # clustered one, K = 2, 4, 9, with fixed cuts and rebalanced.
        for sc in 1 2 clustered; do
            ticks=200
            [[ $sc == 1 ]] || ticks=120
            .carry/myriad sim --scenario $sc --ticks $ticks --backend cpu --json 2>/dev/null ||
                fail "sim scenario $sc on cpu failed"
            for k in 2 4 9; do
                .carry/myriad sim --scenario $sc --ticks $ticks --backend cuda --zones $k --gpus "$gpus" --json 2>/dev/null ||
                    fail "sim scenario $sc, $k zones failed"
                # The same with cuts that follow the objects (every 20 ticks).
                .carry/myriad sim --scenario $sc --ticks $ticks --backend cuda --zones $k --gpus "$gpus" --json \
                    --rebalance --rebalance-every 20 2>/dev/null || fail "sim scenario $sc, $k zones, rebalanced failed"
            done
        done
        # Scenario 3 and four times scenario 3 (1,040,000 dynamic, 400,000 static on
        # twice the side): one process on one GPU, then 2 and 4 zones on threads of one
        # process sharing the GPUs there are, twice each, the older build interleaved.
        big=(--scenario custom --dynamic 1040000 --users 40000 --static 400000 --world-size 2048)
        for world in 3 big; do
            if [[ $world == 3 ]]; then w=(--scenario 3); else w=("${big[@]}"); fi
            for round in 1 2; do
                for b in myriad before/myriad; do
                    [[ -x .carry/$b ]] || continue
                    tag=after
                    [[ $b == myriad ]] || tag=before
                    run=(".carry/$b" sim "${w[@]}" --ticks 100 --backend cuda --json)
                    for k in 1 2 4; do
                        if [[ $k == 1 ]]; then z=(); else z=(--zones "$k" --gpus "$gpus"); fi
                        if out_line=$("${run[@]}" "${z[@]}" 2>>"$out/zones-stderr.log"); then
                            echo "${out_line%\}},\"build\":\"$tag\",\"world\":\"$world\",\"round\":$round}"
                        else
                            fail "sim $world, $k zones ($tag) failed"
                        fi
                    done
                done
            done
        done
        if [[ -n $nats_pid ]]; then
            if out_line=$(.carry/myriad sim --scenario 3 --ticks 100 --backend cuda --json --zones 2 --gpus "$gpus" \
                --nats nats://127.0.0.1:4222 2>>"$out/zones-stderr.log"); then
                echo "${out_line%\}},\"world\":\"3\"}"
            else
                fail "sim scenario 3, 2 zones over NATS failed"
            fi
        fi
        # The moving crowd (a crowd walking across the cuts) in 4 zones on cuda, with
        # fixed cuts and with rebalancing, against one process on cpu.
        mc=(--scenario moving-crowd --ticks 2000 --json)
        for z in "--backend cpu" "--backend cuda --zones 4" "--backend cuda --zones 4 --rebalance"; do
            read -ra zz <<<"$z"
            if out_line=$(.carry/myriad sim "${mc[@]}" "${zz[@]}" 2>>"$out/zones-stderr.log"); then
                echo "${out_line%\}},\"world\":\"moving-crowd\"}"
            else
                fail "sim moving crowd $z failed"
            fi
        done
    } | tee "$out/zones.jsonl" | python3 -c '
import json, sys
rows = [json.loads(l) for l in sys.stdin if l.strip()]
want = {}
ok = len(rows) >= 23
for r in rows:
    z = r.get("zoned")
    before = r.get("build") == "before"
    key = r.get("world", r["scenario"])
    if z is None and not before:
        want[key] = r["state_hash"]
    same = r["state_hash"] == want.get(key)
    ok = ok and (same or before)
    if z is not None and "slowest_over_mean" in z:
        print("  %s: cut moves %d, slowest zone physics / mean %s, most owned / mean %s (whole run, last third)" % (
            key, z["cut_moves"], [round(x, 2) for x in z["slowest_over_mean"]],
            [round(x, 2) for x in z["most_owned_over_mean"]]))
    print("%s sim %s%s, %d ticks, %s%s: %s, %.3f ms a tick, equal to one process: %s%s" % (
        r.get("build", "after"), r.get("world", r["scenario"]), " round %s" % r["round"] if "round" in r else "",
        r["ticks"], r["description"], "" if z is None else " over " + z["fabric"],
        r["state_hash"], r["mean_tick_ms"], same,
        "" if z is None else "; per zone: physics %s, overhead %s, wait %s ms a tick; %d ghost records, %.1f MB" % (
            [round(x, 2) for x in z["physics_ms"]], [round(x, 2) for x in z["overhead_ms"]], [round(x, 2) for x in z["wait_ms"]],
            z["ghost_records"], z["fabric_bytes"] / 1e6)))
sys.exit(0 if ok else 1)
' || fail "zones: a zoned run differs from one process (or runs are missing)"
    if [[ -n $nats_pid ]]; then
        .carry/myriad cluster --zones 2 --gpus "$gpus" --scenario 3 --ticks 100 --backend cuda --json 2>"$out/cluster.log" |
            tee "$out/cluster.json"
        [[ ${PIPESTATUS[0]} == 0 ]] || fail "cluster of 2 zones failed"
        kill "$nats_pid"
    fi
fi

if [[ $mode == zprofile ]]; then
    # Where a zone's tick goes on one GPU. Parts (ZPROFILE, default all three):
    # split: scenario 3 in one process, a quarter of it alone (one zone's share, stepped
    # by nobody else) and in 4 zones sharing the GPU, three times each; threads: 4 zones
    # against the size of rayon's pool (the zones' threads and the pool's share the
    # host's cores); kernels: per-kernel device times (MYRIAD_CUDA_PROFILE=1).
    parts=" ${ZPROFILE:-split threads kernels} "
    quarter=(--scenario custom --dynamic 65000 --users 2500 --static 25000 --world-size 512)
    if [[ $parts == *" split "* ]]; then
        for _ in 1 2 3; do
            for args in "--scenario 3" "${quarter[*]}" "--scenario 3 --zones 4 --gpus 1"; do
                echo "=== sim $args"
                # shellcheck disable=SC2086
                .carry/myriad sim $args --ticks 100 --backend cuda 2>>"$out/zprofile-stderr.log" |
                    grep -E "tick|per zone|of which|state hash" || fail "sim $args failed"
            done
        done 2>&1 | tee "$out/zprofile.log"
    fi
    if [[ $parts == *" threads "* ]]; then
        for threads in 4 8 12 16 4 8 12 16; do
            echo "=== RAYON_NUM_THREADS=$threads sim --scenario 3 --zones 4 --gpus 1"
            RAYON_NUM_THREADS=$threads .carry/myriad sim --scenario 3 --zones 4 --gpus 1 --ticks 100 --backend cuda \
                2>>"$out/zprofile-stderr.log" | grep -E "ticks |per zone|of which" || fail "sim with $threads threads failed"
        done 2>&1 | tee "$out/zprofile-threads.log"
    fi
    if [[ $parts == *" kernels "* ]]; then
        for args in "--scenario 3" "--scenario 3 --zones 4 --gpus 1"; do
            echo "=== profiled: sim $args"
            # shellcheck disable=SC2086
            MYRIAD_CUDA_PROFILE=1 .carry/myriad sim $args --ticks 100 --backend cuda 2>&1 | tail -60
        done >"$out/zprofile-kernels.log" 2>&1
        tail -c 6000 "$out/zprofile-kernels.log"
    fi
fi

if [[ $mode == rebalance ]]; then
    if [[ -x .carry/nats-server ]]; then
        .carry/nats-server -a 127.0.0.1 -p 4222 -js -sd /tmp/myriad-nats >/dev/null 2>&1 &
        rb_nats=$!
        sleep 1
        for backend in ${REBALANCE_BACKENDS:-cpu cuda}; do
            echo "=== rebalance-live on $backend"
            # Each zone process gets a share of the host's cores for its rayon pool.
            RAYON_NUM_THREADS=$(($(nproc) / 4)) bash scripts/rebalance-live.sh -b .carry/myriad -k 4 -x "$backend" \
                -o "$out/rebalance-$backend" || fail "rebalance-live on $backend failed"
        done 2>&1 | tee "$out/rebalance.log"
        kill "$rb_nats"
    else
        fail "rebalance: no .carry/nats-server"
    fi
fi

if [[ $mode == million ]]; then
    if [[ -x .carry/nats-server ]]; then
        .carry/nats-server -a 127.0.0.1 -p 4222 -js -sd /tmp/myriad-nats >/dev/null 2>&1 &
        ml_nats=$!
        sleep 1
        # One run per "DYNAMIC:MAP" of MILLION_RUNS (MAP: the reference scenario whose
        # map, statics and users the world has).
        # With a build in .carry/before/, each run goes with it first, then with this one.
        builds=(this)
        if [[ -x .carry/before/myriad ]]; then builds=(before this); fi
        for run in ${MILLION_RUNS:-${MILLION_DYNAMIC:-1000000}:3}; do
            for build in "${builds[@]}"; do
                bin=.carry/myriad
                if [[ $build == before ]]; then bin=.carry/before/myriad; fi
                echo "=== ${run%%:*} dynamic objects on scenario ${run##*:}'s map, $build build"
                bash scripts/million-live.sh -b "$bin" -d "${MILLION_SECONDS:-60}" -n "${run%%:*}" -s "${run##*:}" \
                    -o "$out/million-${run%%:*}-$build" 2>&1 || fail "million-live $run ($build) failed"
            done
        done | tee "$out/million.log"
        kill "$ml_nats"
    else
        fail "million: no .carry/nats-server"
    fi
fi

if [[ $mode == players ]]; then
    # 50,000 players at 20 a socket are 2,500 sockets, with a margin.
    ulimit -n 65536 || true
    for run in $(seq 1 "${PLAYERS_RUNS:-2}"); do
        for scenario in ${PLAYERS_SCENARIOS:-3 4}; do
            echo "=== scenario $scenario, run $run"
            if [[ $scenario == 3 ]]; then
                timeout "${PLAYERS_TIMEOUT:-0}" .carry/myriad bench --scenario 3 --backend cuda --ticks 90 \
                    --warmup 30 --aoi-size 14,100 \
                    --out "$out/bench/players-s3-$run" >"$out/players-s3-$run.md" 2>>"$out/players.log" ||
                    fail "bench scenario 3 run $run failed"
            else
                timeout "${PLAYERS_TIMEOUT:-0}" .carry/myriad bench --scenario 4 --backend cuda --ticks 30 \
                    --warmup 3 --aoi-size "${PLAYERS_AOI:-14,100}" --bots-per-socket 20 \
                    --out "$out/bench/players-s4-$run" >"$out/players-s4-$run.md" 2>>"$out/players.log" ||
                    fail "bench scenario 4 run $run failed"
            fi
            grep -E "^\| $scenario \|" "$out/players-s$scenario-$run.md"
        done
    done 2>&1 | tee "$out/players.txt"
fi

if [[ $mode == replication ]]; then
    nproc
    for bin in .carry/before/myriad .carry/myriad; do
        [[ -x $bin && ${REPLICATION_S3:-1} == 1 ]] || continue
        tag=$([[ $bin == .carry/myriad ]] && echo after || echo before)
        echo "=== $tag"
        timeout -k 5 "${REPLICATION_TIMEOUT:-0}" $bin bench --scenario 3 --backend cuda --ticks 60 --warmup 30 \
            --aoi-size "${REPLICATION_AOI:-14,100}" \
            --out "$out/bench/replication-$tag" >"$out/replication-$tag.md" 2>>"$out/replication.log" ||
            fail "bench scenario 3 ($tag) failed"
        grep -E '^\| 3 \|' "$out/replication-$tag.md"
    done 2>&1 | tee "$out/replication.txt"
    if [[ ${REPLICATION_LOSSY:-1} == 1 ]]; then
        echo "=== after, shadow through 5 % loss, 100 ± 20 ms" | tee -a "$out/replication.txt"
        timeout -k 5 "${REPLICATION_TIMEOUT:-0}" .carry/myriad bench --scenario 3 --backend cuda --ticks 60 \
            --warmup 30 --aoi-size "${REPLICATION_AOI:-14,100}" \
            --shadow-budget-kbps 244 --shadow-loss 0.05 --shadow-delay-ms 100 --shadow-jitter-ms 20 \
            --out "$out/bench/replication-lossy" >"$out/replication-lossy.md" 2>>"$out/replication.log" ||
            fail "bench scenario 3 (lossy shadow) failed"
        grep -E '^\| 3 \|' "$out/replication-lossy.md" | tee -a "$out/replication.txt"
    fi
    if [[ ${REPLICATION_S2:-0} == 1 ]]; then
        for bin in .carry/before/myriad .carry/myriad; do
            [[ -x $bin ]] || continue
            tag=$([[ $bin == .carry/myriad ]] && echo after || echo before)
            echo "=== $tag, scenario 2 at AOI 100" | tee -a "$out/replication.txt"
            $bin bench --scenario 2 --backend cuda --ticks 60 --warmup 30 --aoi-size 100 --quality-players 0 \
                --out "$out/bench/replication-s2-$tag" >"$out/replication-s2-$tag.md" 2>>"$out/replication.log" ||
                fail "bench scenario 2 ($tag) failed"
            grep -E '^\| 2 \|' "$out/replication-s2-$tag.md" | tee -a "$out/replication.txt"
        done
    fi
    if [[ ${REPLICATION_PROFILE:-1} == 1 ]]; then
        # Where the device time of a tick at AOI 100 goes, kernel by kernel (the build
        # before too, when there is one).
        for aoi in ${REPLICATION_PROFILE_AOI:-100}; do
            for bin in .carry/before/myriad .carry/myriad; do
                [[ -x $bin ]] || continue
                [[ $bin == .carry/myriad || ${REPLICATION_PROFILE_BEFORE:-1} == 1 ]] || continue
                tag=$([[ $bin == .carry/myriad ]] && echo after || echo before)-$aoi
                echo "=== $tag, per-kernel device time at AOI $aoi (MYRIAD_CUDA_PROFILE=1)" |
                    tee -a "$out/replication.txt"
                MYRIAD_CUDA_PROFILE=1 $bin bench --scenario 3 --backend cuda --ticks 20 --warmup 10 --aoi-size "$aoi" \
                    --quality-players 0 --out "$out/bench/replication-profile-$tag" \
                    >"$out/replication-profile-$tag.md" 2>"$out/replication-profile-$tag.log" ||
                    fail "profiled bench scenario 3 ($tag) failed"
                grep -E -A40 "per-kernel" "$out/replication-profile-$tag.log" | grep -E "per-kernel|^\|" |
                    tee -a "$out/replication.txt"
            done
        done
    fi
    if [[ ${REPLICATION_S4:-0} == 1 ]]; then
        # Scenario 4 at AOI 14, before (when there is a build before) and after;
        # REPLICATION_S4_PROFILE=1 profiles them (per-kernel and host spans).
        ulimit -n 65536 || true
        profile=${REPLICATION_S4_PROFILE:-0}
        for bin in .carry/before/myriad .carry/myriad; do
            [[ -x $bin ]] || continue
            tag=$([[ $bin == .carry/myriad ]] && echo after || echo before)
            echo "=== $tag, scenario 4 at AOI ${REPLICATION_S4_AOI:-14} (MYRIAD_CUDA_PROFILE=$profile)" |
                tee -a "$out/replication.txt"
            MYRIAD_CUDA_PROFILE=$profile timeout "${REPLICATION_S4_TIMEOUT:-0}" $bin bench --scenario 4 --backend cuda \
                --ticks 20 --warmup 3 --aoi-size "${REPLICATION_S4_AOI:-14}" --bots-per-socket 20 --quality-players 0 \
                --out "$out/bench/replication-s4-$tag" >"$out/replication-s4-$tag.md" 2>"$out/replication-s4-$tag.log" ||
                fail "bench scenario 4 ($tag) failed"
            grep -E '^\| 4 \|' "$out/replication-s4-$tag.md" | tee -a "$out/replication.txt"
            if [[ $profile == 1 ]]; then
                grep -E -A45 "per-kernel" "$out/replication-s4-$tag.log" | grep -E "per-kernel|^\|" |
                    tee -a "$out/replication.txt"
            fi
        done
    fi
fi

if [[ $mode == flood ]]; then
    DURATION=8 bash scripts/flood-figures.sh .carry/myriad .carry/myriad "$out/flood" session garbage oversized busy ||
        fail "flood figures failed"
    SERVE_ARGS="--set receive_thread=false" DURATION=8 bash scripts/flood-figures.sh .carry/myriad .carry/myriad \
        "$out/flood-inline" session garbage || fail "flood figures with receive_thread=false failed"
    nproc
fi

if [[ $mode == table ]]; then
    # Outside $OUT: the device tool brings back a few files only, so they travel as one.
    dir=$(mktemp -d)/table
    mkdir -p "$dir"
    builds=(.carry/myriad)
    [[ -x .carry/before/myriad ]] && builds=(.carry/before/myriad .carry/myriad)
    which_build() { if [[ $1 == .carry/myriad ]]; then echo after; else echo before; fi; }
    keep() { tar -C "$dir/.." -czf "$out/table.tgz" table; }
    # One run: a log name, a time limit, the build, then its arguments.
    # Each run's log starts with the host's load and ends with its seconds: a host whose
    # other tenants took its cores shows there (one such H100 ran the same runs twice as
    # slowly in the second half of a call, 2026-12-07).
    measure() {
        local log=$1 limit=$2 bin=$3 started=$SECONDS
        shift 3
        echo "load before: $(cat /proc/loadavg)" >"$dir/$log.txt"
        timeout -k 5 "$limit" "$bin" "$@" >>"$dir/$log.txt" 2>&1 || fail "table: $log ($bin $*)"
        echo "seconds: $((SECONDS - started)), load after: $(cat /proc/loadavg)" >>"$dir/$log.txt"
        grep -E '^\| (2|3|4|sweep-[0-9]+) \||state_hash|^load before|^seconds' "$dir/$log.txt" | sed "s/^/$log: /"
        keep
    }
    ulimit -n 65536 || true
    s4=(bench --scenario 4 --backend cuda --ticks 20 --warmup 3 --bots-per-socket 20 --quality-players 0)
    s3=(bench --scenario 3 --backend cuda --ticks 60 --warmup 30 --quality-players 0)
    s2=(bench --scenario 2 --backend cuda --ticks 60 --warmup 30 --aoi-size 100 --quality-players 0)
    physics=(bench --scenario 3 --backend cuda --ticks 30 --warmup 3 --physics-only --sweep 2000000)
    # A measured run's arguments and time limit, by name (a table step, or what a
    # profile-NAME step profiles); false for an unknown name.
    run_of() {
        case $1 in
        physics) args=("${physics[@]}") limit=90 ;;
        s4-14) args=("${s4[@]}" --aoi-size 14) limit=120 ;;
        s4-100) args=("${s4[@]}" --aoi-size 100) limit=240 ;;
        s4) args=("${s4[@]}" --aoi-size "14,100") limit=300 ;;
        s3) args=("${s3[@]}" --aoi-size "14,100") limit=150 ;;
        s3-14 | s3-100) args=("${s3[@]}" --aoi-size "${1#s3-}") limit=160 ;;
        s2-100) args=("${s2[@]}") limit=60 ;;
        zones) args=(sim --scenario 3 --ticks 60 --backend cuda --zones 4 --json) limit=90 ;;
        *) return 1 ;;
        esac
    }
    # Each step in turn, so a call cut short still brings back the first steps whole;
    # within a step the builds alternate round by round.
    for step in ${TABLE_STEPS:-physics s4-14 s2-100 profile-s4-14 profile-s4-100 profile-s2-100 profile-physics s4-100 zones}; do
        if [[ $step == chunks-* ]] && run_of "${step#chunks-}"; then
            # This build's device outbound in chunks of players (MYRIAD_REPLICA_CHUNKS,
            # MYRIAD_REPLICA_TAPER) for each of TABLE_CHUNKS (default "1 4"), alternating
            # round by round.
            for r in $(seq 1 "${TABLE_ROUNDS:-2}"); do
                for plan in ${TABLE_CHUNKS:-1 4}; do
                    n=${plan%%:*} taper=measured
                    [[ $plan == *:* ]] && taper=${plan#*:}
                    MYRIAD_REPLICA_CHUNKS=$n MYRIAD_REPLICA_TAPER=$taper \
                        measure "$step-${plan/:/-}-$r" "$limit" .carry/myriad "${args[@]}"
                done
            done
        elif [[ $step == refits ]]; then
            # The physics with the dynamic tree refit for N steps between builds, for each
            # N of TABLE_REFITS, this build only, alternating N round by round.
            for r in $(seq 1 "${TABLE_ROUNDS:-2}"); do
                for n in ${TABLE_REFITS:-0 2 4 8}; do
                    MYRIAD_TREE_REFITS=$n measure "refits-$n-$r" 90 .carry/myriad "${physics[@]}"
                done
            done
        elif [[ $step == profile-* && $step != profile-zones ]] && run_of "${step#profile-}"; then
            MYRIAD_CUDA_PROFILE=1 measure "$step" "$limit" .carry/myriad "${args[@]}"
        elif [[ $step != profile-* ]] && run_of "$step"; then
            rounds=${TABLE_ROUNDS:-2}
            [[ $step == zones ]] && rounds=1
            for r in $(seq 1 "$rounds"); do
                for b in "${builds[@]}"; do
                    measure "$step-$(which_build "$b")-$r" "$limit" "$b" "${args[@]}"
                done
            done
        else
            fail "table: unknown step $step"
        fi
    done
fi

if [[ $mode == host ]]; then
    nproc
    for bin in .carry/before/myriad .carry/myriad; do
        [[ -x $bin ]] || continue
        echo "=== $bin"
        for _ in 1 2; do
            $bin bench --scenario 2 --backend cpu --ticks 30 --warmup 3 --aoi-size 14,100 \
                2>>"$out/host.log" | grep -E '^\| 2 \| cpu \| (14|100) ' || fail "$bin bench scenario 2 failed"
        done
    done
    if [[ -x .carry/aoi_query ]]; then
        for sc in 2 3; do .carry/aoi_query "$sc" 100 || fail "aoi_query scenario $sc failed"; done
    fi
fi

# The device tool brings back a few files only: the bench's tables and plots as one.
if [[ -d $out/bench ]]; then
    tar -C "$out" -czf "$out/bench.tgz" bench && rm -rf "$out/bench"
fi
if [[ -s $failures ]]; then
    echo "=== FAILED ($(wc -l <"$failures")):"
    sed 's/^/  /' "$failures"
    exit 1
fi
echo "=== all passed"
