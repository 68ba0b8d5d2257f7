#!/usr/bin/env bash
# Builds (release) the myriad-cuda test binaries and the `myriad` binary here, strips
# them, and copies them into .carry/ (ignored by git) for the lent GPU machine; then
# prints the `run` call that executes scripts/gpu-run.sh there.
#
# Usage: scripts/gpu-build.sh        (CARGO_TARGET_DIR is honoured)
#        PARTS=host BEFORE=path/to/an/older/myriad scripts/gpu-build.sh
#        (only `myriad`, the AOI query example and the older build in .carry/before/,
#        for MODE=host of scripts/gpu-run.sh; BEFORE alone adds the older build to the
#        whole bundle, for MODE=zones)
set -euo pipefail
cd "$(dirname "$0")/.."
carry=.carry
rm -rf "$carry"
mkdir -p "$carry/tests"
jobs=${JOBS:-1}
parts=${PARTS:-all}

# Test binaries of myriad-cuda and the server's device outbound test; cargo's JSON
# messages name each executable.
[[ $parts == host ]] || {
    nice -n 10 cargo test --release -j "$jobs" -p myriad-cuda --no-run --message-format=json
    nice -n 10 cargo test --release -j "$jobs" -p myriad-server --test device_outbound --no-run --message-format=json
} 2>"$carry/build.log" |
    python3 -c '
import json, sys
for line in sys.stdin:
    try:
        m = json.loads(line)
    except ValueError:
        continue
    if m.get("reason") == "compiler-artifact" and m.get("executable") and m["target"]["kind"] == ["test"]:
        print(m["target"]["name"], m["executable"])
' | while read -r name exe; do
    cp "$exe" "$carry/tests/$name"
done
nice -n 10 cargo build --release -j "$jobs" -p myriad --bin myriad
target=${CARGO_TARGET_DIR:-target}
cp "$target/release/myriad" "$carry/myriad"
if [[ $parts == host ]]; then
    nice -n 10 cargo build --release -j "$jobs" -p myriad-physics --example aoi_query
    cp "$target/release/examples/aoi_query" "$carry/aoi_query"
    strip "$carry/aoi_query"
fi
if [[ -n ${BEFORE:-} ]]; then
    mkdir -p "$carry/before"
    cp "$BEFORE" "$carry/before/myriad"
    strip "$carry/before/myriad"
    # Two builds, the test binaries and the tree together pass the device tool's 64 MiB;
    # scripts/gpu-run.sh unpacks it.
    gzip -9 "$carry/before/myriad"
fi
strip "$carry/myriad"
if compgen -G "$carry/tests/*" >/dev/null; then strip "$carry"/tests/*; fi
# The zones' checks need a NATS server; the GPU machine has none installed.
nats=$(command -v nats-server || echo /usr/sbin/nats-server)
if [[ -x $nats ]]; then cp "$nats" "$carry/nats-server"; fi
du -sh "$carry"
ls -l "$carry" "$carry/tests"
cat <<'MSG'

Now call the device tool:
  run(command="bash scripts/gpu-run.sh", carry=[".carry"], timeout_s=600)
  (MODE=zones on kind nvidia-h200-x2 for the zones across two GPUs)
MSG
