#!/usr/bin/env bash
# The scaling bench (bench/bench_scaling.py) on a lent machine of many cores, where neither ../shared nor
# PyPI nor redis-server are (/work/shared/DEVICE.md says why each step is needed). Two steps:
#
#   bench/scaling_device.sh prepare        here: gathers what the run needs into .device/ (git ignores it;
#                                          about 40 MB: the model, 60 frames, cp312 wheels, redis-server)
#   bench/scaling_device.sh compare [ARGS] there: settings side by side at W = cores - 1 and a worker's frame
#                                          part by part alone and contended (see compare() below)
#   bench/scaling_device.sh run [ARGS]     there, from the repository root (the `run` tool with carry
#                                          [".device"]): installs the wheels into /tmp/site, runs
#                                          bench_scaling.py in four parts (ceiling, service, wait, and the
#                                          service at W = cores - 1 without the pipelined worker; ARGS are added
#                                          to the last three) and writes $OUT/scaling-{ceiling,service,wait,
#                                          service-no-prefetch}.json (bench/results/ without $OUT); WORKERS,
#                                          WAIT_WORKERS and CEILING_S, SERVICE_S, WAIT_S, NO_PREFETCH_S (each
#                                          part's limit) change the defaults
#
# Plot it here afterwards: .venv/bin/python bench/bench_scaling.py --plot FILE.json (matplotlib is not carried).
set -euo pipefail
cd "$(dirname "$0")/.."

DEVICE=.device
SHARED=${ARCLOUD_SHARED:-../shared}
MODEL=yolo11n-seg-fp32-640.onnx
FRAMES=60  # every STRIDE-th frame of 7-Scenes redkitchen, as bench_scaling.py's defaults take them
STRIDE=10
# What the machine there lacks (DEVICE.md); versions from constraints.txt.
WHEELS="fastapi starlette uvicorn pydantic pydantic_core pydantic-settings python-dotenv python-multipart redis
annotated-types typing-inspection annotated-doc httptools opentelemetry-api hiredis"
# Pure-Python requirements of those that the machine had; carried anyway, so a machine without them runs too.
WHEELS="$WHEELS typing_extensions importlib_metadata zipp click h11 anyio idna"

prepare() {
    rm -rf "$DEVICE"
    mkdir -p "$DEVICE"/wheels "$DEVICE"/bin "$DEVICE"/lib "$DEVICE"/shared/models "$DEVICE"/shared/data/7scenes-redkitchen
    grep -qx "$DEVICE/" .git/info/exclude 2>/dev/null || echo "$DEVICE/" >> .git/info/exclude
    cp "$SHARED/models/$MODEL" "$DEVICE/shared/models/"
    local scene="$SHARED/data/7scenes-redkitchen"
    cp "$scene/camera-intrinsics.txt" "$scene/gravity-direction.txt" "$DEVICE/shared/data/7scenes-redkitchen/"
    for ((i = 0; i < FRAMES * STRIDE; i += STRIDE)); do
        cp "$scene"/frame-$(printf %06d $i).{color.jpg,depth.png,pose.txt} "$DEVICE/shared/data/7scenes-redkitchen/"
    done
    local pins=()
    for name in $WHEELS; do
        local pin
        pin=$(grep -i "^${name//[-_]/[-_]}==" constraints.txt) || { echo "no pin for $name in constraints.txt" >&2; exit 1; }
        pins+=("$pin")
    done
    .venv/bin/python -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
        --platform manylinux2014_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux_2_28_x86_64 \
        -d "$DEVICE/wheels" "${pins[@]}"
    # Debian's redis-server is the same binary as redis-check-rdb; it needs these two libraries.
    cp "$(command -v redis-check-rdb)" "$DEVICE/bin/redis-server"
    cp /lib/x86_64-linux-gnu/liblzf.so.1 /lib/x86_64-linux-gnu/libjemalloc.so.2 "$DEVICE/lib/"
    du -sh "$DEVICE"
}

# The carried wheels installed, redis-server and the carried assets on the paths; fails in seconds, not after
# the ceiling, when something the service imports is missing.
setup() {
    python=${PYTHON:-python3}
    [[ -n ${NO_INSTALL:-} ]] || "$python" -m pip install -q --no-index --no-deps --target /tmp/site "$DEVICE"/wheels/*.whl
    export PATH="$PWD/$DEVICE/bin:$PATH" LD_LIBRARY_PATH="$PWD/$DEVICE/lib" PYTHONPATH="/tmp/site:$PWD/src"
    export ARCLOUD_SHARED="$PWD/$DEVICE/shared"
    out=${OUT:-bench/results}
    cores=$(nproc)
    echo "cores $cores"
    "$python" -c "import arcloud.service.app, arcloud.service.worker, fastapi, uvicorn, redis, onnxruntime"
    redis-server --version
}

run() {
    setup
    # In parts, each with its own limit and file, so that a part that runs long leaves the others' results.
    local bench=("$python" bench/bench_scaling.py --frames "$FRAMES" --stride 1 --api-processes 2 --service-frames 32)
    timeout "${CEILING_S:-90}" "${bench[@]}" --parts ceiling --ceiling-processes "1,4,8,$((cores - 1)),$cores" \
        --out "$out/scaling-ceiling.json" || echo "ceiling part failed or ran out of time"
    timeout "${SERVICE_S:-260}" "${bench[@]}" --parts service --ceiling-from "$out/scaling-ceiling.json" \
        --workers "${WORKERS:-1,4,8,$((cores - 1))}" --out "$out/scaling-service.json" "$@" || echo "service part failed or ran out of time"
    timeout "${WAIT_S:-110}" "${bench[@]}" --parts wait --ceiling-from "$out/scaling-ceiling.json" \
        --wait-workers "${WAIT_WORKERS:-1,4,16}" --wait-phase-s 2 --out "$out/scaling-wait.json" "$@" || echo "wait part failed or ran out of time"
    # The same service without the pipelined worker, at the most workers: what prefetching gives on real cores.
    timeout "${NO_PREFETCH_S:-90}" "${bench[@]}" --parts service --ceiling-from "$out/scaling-ceiling.json" \
        --workers "$((cores - 1))" --worker-prefetch off --out "$out/scaling-service-no-prefetch.json" "$@" \
        || echo "no-prefetch part failed or ran out of time"
}

# The service's defaults at W = SWEEP (4,8), then settings side by side at W = cores - 1 (one map and 8 maps each,
# against one ceiling; CONFIGS: name:prefetch:params ..., params JSON overrides of Params or empty; SWEEP set and
# empty skips the sweep, NO_HOLD set skips the hold and the profiles (device time is short); CONFIG_S: each
# one's limit), then the hold a frame's locks last (bench/bench_hold.py, idle and beside W sessions), then what a
# worker's frame costs part by part alone and with W copies at once (bench/profile_worker.py: where contention
# adds). Eight files under $OUT at most come back: seven JSON here with one setting, and a log.
compare() {
    setup
    local w=$((cores - 1)) name prefetch params
    local bench=("$python" bench/bench_scaling.py --frames "$FRAMES" --stride 1 --api-processes 2 --service-frames 32)
    timeout "${CEILING_S:-90}" "${bench[@]}" --parts ceiling --ceiling-processes "1,${SWEEP:-4,8},$w" --ceiling-s 6 \
        --out "$out/compare-ceiling.json" || echo "ceiling failed or ran out of time"
    # The service's defaults at fewer workers: the ratio per W.
    [[ -z ${SWEEP-x} ]] || timeout "${SWEEP_S:-100}" "${bench[@]}" --parts service --ceiling-from "$out/compare-ceiling.json" \
        --workers "${SWEEP:-4,8}" --out "$out/compare-sweep.json" "$@" || echo "sweep failed or ran out of time"
    for config in ${CONFIGS:-defaults:off:}; do
        IFS=: read -r name prefetch params <<<"$config"
        timeout "${CONFIG_S:-100}" "${bench[@]}" --parts service --ceiling-from "$out/compare-ceiling.json" --workers "$w" \
            --worker-prefetch "$prefetch" ${params:+--params "$params"} --out "$out/compare-$name.json" "$@" \
            || echo "$name failed or ran out of time"
    done
    [[ -z ${NO_HOLD:-} ]] || return 0
    # How long a frame holds its locks (what bounds one hot map), on idle cores and beside W busy sessions.
    timeout 90 "$python" bench/bench_hold.py --frames "$FRAMES" --stride 1 --out "$out/hold-idle.json" >/dev/null \
        || echo "hold (idle) failed"
    timeout 150 "$python" bench/bench_hold.py --frames "$FRAMES" --stride 1 --busy "$w" --out "$out/hold-busy.json" >/dev/null \
        || echo "hold (busy) failed"
    local profile=("$python" bench/profile_worker.py --frames "${PROFILE_FRAMES:-30}")
    timeout 60 "${profile[@]}" --out "$out/profile-alone.json" >/dev/null || echo "profile alone failed"
    local i pids=()
    for ((i = 0; i < w; i++)); do
        timeout 120 "${profile[@]}" --out "/tmp/profile-$i.json" >/dev/null &
        pids+=($!)
    done
    wait "${pids[@]}" || echo "a contended profile failed"
    "$python" - "$out/profile-contention.json" /tmp/profile-*.json <<'PY'
import json, sys
runs = [json.load(open(p)) for p in sys.argv[2:]]
json.dump({"processes": len(runs), "runs": runs}, open(sys.argv[1], "w"), indent=1)
PY
}

case "${1:-}" in
    prepare) prepare ;;
    run) shift; run "$@" ;;
    compare) shift; compare "$@" ;;
    *) echo "usage: $0 prepare | run [bench_scaling.py arguments] | compare [bench_scaling.py arguments]" >&2; exit 2 ;;
esac
