#!/usr/bin/env bash
# Checks, without a GPU, that scripts/gpu-run.sh (MODE=tests) fails when it should: it
# runs the script on fake bundles in a temp dir (.carry/ with test binaries and a
# `myriad` that are shell scripts) and asserts that
#   - a passing bundle exits 0;
#   - a failing test binary makes it exit non-zero, naming that binary;
#   - a CUDA hash that differs from the CPU's makes it exit non-zero, naming each
#     comparison that differs;
#   - a `myriad sim` that fails makes it exit non-zero, naming that run.
# Run by .ci/run.
set -euo pipefail
script=$(cd "$(dirname "$0")" && pwd)/gpu-run.sh
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT

# A bundle in $1: two test binaries (the second fails when FAIL_TEST=1) and a `myriad`
# whose cuda hash is FAKE_CUDA_HASH (default: the CPU's) and whose cuda-naive run fails
# when FAIL_SIM=1.
bundle() {
    mkdir -p "$1/.carry/tests"
    printf '#!/usr/bin/env bash\necho "test result: ok. 1 passed"\n' >"$1/.carry/tests/passes"
    cat >"$1/.carry/tests/breaks_when_asked" <<'SH'
#!/usr/bin/env bash
[[ ${FAIL_TEST:-0} == 0 ]] || { echo "test broken ... FAILED"; exit 101; }
echo "test result: ok. 1 passed"
SH
    cat >"$1/.carry/myriad" <<'SH'
#!/usr/bin/env bash
# A stand-in for `myriad sim ... --json`: one JSON line with the arguments' figures.
backend=cpu dynamic=0 ticks=0
while (($#)); do
    case $1 in
    --backend) backend=$2; shift ;;
    --dynamic) dynamic=$2; shift ;;
    --ticks) ticks=$2; shift ;;
    esac
    shift
done
[[ $backend == cuda-naive && ${FAIL_SIM:-0} == 1 ]] && exit 1
hash=00000000000000aa
[[ $backend == cpu ]] || hash=${FAKE_CUDA_HASH:-$hash}
printf '{"backend":"%s","dynamic":%s,"ticks":%s,"state_hash":"%s","mean_tick_ms":1.0}\n' \
    "$backend" "$dynamic" "$ticks" "$hash"
SH
    chmod +x "$1/.carry/myriad" "$1"/.carry/tests/*
}

# Runs gpu-run.sh in a fresh bundle with the given environment; prints its output to
# $tmp/NAME.log and returns its exit status.
run() {
    local name=$1
    shift
    bundle "$tmp/$name"
    (cd "$tmp/$name" && env "$@" MODE=tests OUT="$tmp/$name/out" bash "$script") >"$tmp/$name.log" 2>&1
}

checks=0
expect() {
    local name=$1 want=$2 got=$3
    checks=$((checks + 1))
    if [[ $want != "$got" ]]; then
        echo "check-gpu-run: $name: exit status $got, want $want; its output:" >&2
        cat "$tmp/$name.log" >&2
        exit 1
    fi
}
names() {
    local name=$1
    shift
    for want in "$@"; do
        checks=$((checks + 1))
        if ! grep -qF -- "$want" "$tmp/$name.log"; then
            echo "check-gpu-run: $name: the output does not name \"$want\"; it was:" >&2
            cat "$tmp/$name.log" >&2
            exit 1
        fi
    done
}

st=0; run passing || st=$?
expect passing 0 "$st"
names passing "=== all passed"

st=0; run failing-test FAIL_TEST=1 || st=$?
expect failing-test 1 "$st"
names failing-test "=== FAILED (1)" "test binary breaks_when_asked failed"

st=0; run hash-mismatch FAKE_CUDA_HASH=00000000000000bb || st=$?
expect hash-mismatch 1 "$st"
names hash-mismatch "=== FAILED (2)" "sim scenario 1: the backends hashes differ" \
    "sim large worlds: cpu and cuda hashes differ"

st=0; run failing-sim FAIL_SIM=1 || st=$?
expect failing-sim 1 "$st"
names failing-sim "sim scenario 1 --backend cuda-naive failed" "sim scenario 1: the backends hashes differ"

echo "check-gpu-run: $checks checks passed"
