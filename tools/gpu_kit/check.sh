#!/usr/bin/env bash
# The GPU kit's check: install marl-render from this kit without network, show the GPU and the GL
# driver, run the correctness subset and the benchmarks, and write ONE JSON file. Every stage runs
# under `timeout`, capped so that the whole check ends inside --budget seconds (default 450, i.e.
# 7.5 minutes); a stage with too little time left is recorded as skipped. See README.md.
#
#   bash check.sh [--json FILE] [--budget SECONDS] [--sizes "1024 4096 16384"] [--more "65536"]
#                 [--steps N] [--python PYTHON] [--device cuda] [--readbacks "gpu host"]
#                 [--interop-tests "..."] [--gl-debug-worlds N] [--processes "1 2 4"] [--processes-worlds N]
#   bash check.sh --cpu --python .venv/bin/python --sizes 4 --more "" --tests "..." --render-args "..."
#
# --cpu is the dry run: nothing is installed (PYTHON's own marl-render is used), tensors stay on the
# CPU, GL is whatever EGL finds (Mesa here), and nvidia-smi and the GL packages are left out.
set -u

KIT="$(cd "$(dirname "$0")" && pwd)"
JSON="${OUT:-.}/gpu_check.json"
MODE=gpu
PYTHON=python3
SIZES="1024 4096 16384"
MORE="65536"                      # tried after everything else, while memory and time allow
STEPS=30
PBR_STEPS=100
BUDGET=450
TESTS="$KIT/tests/test_renderer.py $KIT/tests/test_transforms.py"
# The interop's own tests: the real ones (marker gpu: interop frames == host frames, bit for bit, every
# mode; num_processes= on CUDA equal to one process) and the control flow with fakes.
INTEROP_TESTS="$KIT/tests/test_interop_gpu.py $KIT/tests/test_multiprocess_gpu.py $KIT/tests/test_interop.py"
READBACKS=""                      # bench env --readback, side by side in one call (gpu host; --cpu: host pbo)
GL_DEBUG_WORLDS=16384             # the one run with gl-debug #t (the 0x502 errors grew with the worlds)
RENDER_ARGS=""                    # bench render's defaults: 256 worlds x 4 agents at 64 px
DEVICE=""                         # of the env's tensors: cuda (cpu with --cpu)
PROCESSES="1 2 4"                 # num_processes= against one process with all the worlds, in one call
PROCESSES_WORLDS=4096             # ... of cartpole at 64 px

while [ $# -gt 0 ]; do
    case "$1" in
        --json) JSON=$2; shift 2 ;;
        --cpu) MODE=cpu; shift ;;
        --device) DEVICE=$2; shift 2 ;;
        --python) PYTHON=$2; shift 2 ;;
        --sizes) SIZES=$2; shift 2 ;;
        --more) MORE=$2; shift 2 ;;
        --steps) STEPS=$2; shift 2 ;;
        --pbr-steps) PBR_STEPS=$2; shift 2 ;;
        --budget) BUDGET=$2; shift 2 ;;
        --tests) TESTS=$2; shift 2 ;;
        --interop-tests) INTEROP_TESTS=$2; shift 2 ;;
        --readbacks) READBACKS=$2; shift 2 ;;
        --gl-debug-worlds) GL_DEBUG_WORLDS=$2; shift 2 ;;
        --render-args) RENDER_ARGS=$2; shift 2 ;;
        --processes) PROCESSES=$2; shift 2 ;;
        --processes-worlds) PROCESSES_WORLDS=$2; shift 2 ;;
        *) echo "check.sh: unknown argument $1" >&2; exit 2 ;;
    esac
done

START=$(date +%s)
WORK="$(mktemp -d)"               # each stage's command, output, status and time
JSON="$(realpath -m "$JSON")"
# Every stage runs in WORK: started from a checkout's root (as the device tool starts it), `python -m
# marl_render` would import the checkout's marl_render/, which lacks envs/ and glsl/ (an install maps
# them in), instead of the kit's install.
cd "$WORK"
if [ -z "$DEVICE" ]; then
    DEVICE=cuda
    [ "$MODE" = cpu ] && DEVICE=cpu
fi
if [ -z "$READBACKS" ]; then
    READBACKS="gpu host"
    [ "$DEVICE" = cpu ] && READBACKS="host pbo"
fi
COUNT=0

# stage NAME SECONDS COMMAND...: runs COMMAND under a limit of SECONDS, never past the budget
# (20 s are kept for the report); records everything report.py needs. Returns the command's status.
stage() {
    local name=$1 limit=$2
    shift 2
    COUNT=$((COUNT + 1))
    local base
    base="$WORK/$(printf '%02d' "$COUNT")-$name"
    printf '%q ' "$@" > "$base.cmd"
    local left=$((BUDGET - ($(date +%s) - START) - 20))
    if [ "$left" -lt 10 ]; then
        echo "no time left in the ${BUDGET}s budget" > "$base.skipped"
        echo "[check] $name: skipped (no time left)" >&2
        return 99
    fi
    [ "$limit" -gt "$left" ] && limit=$left
    echo "$limit" > "$base.limit"
    echo "[check] $name (at most ${limit}s): $*" >&2
    local t0 t1 rc
    t0=$(date +%s.%N)
    timeout --kill-after=5 "$limit" "$@" > "$base.out" 2> "$base.err"
    rc=$?
    t1=$(date +%s.%N)
    echo "$rc" > "$base.rc"
    echo "$t0 $t1" > "$base.time"
    return "$rc"
}

skip() {  # skip NAME REASON: a stage that does not apply here
    COUNT=$((COUNT + 1))
    echo "$2" > "$WORK/$(printf '%02d' "$COUNT")-$1.skipped"
    echo "[check] $1: skipped ($2)" >&2
}

if [ "$MODE" = gpu ]; then
    # The GL dispatch libraries (libglvnd), unpacked as the device notes say when libEGL is missing.
    if ldconfig -p | grep -q 'libEGL.so.1 '; then
        skip gl-libraries "libEGL.so.1 is installed"
    else
        stage gl-libraries 60 bash -c 'for deb in "$1"/gl/*.deb; do dpkg -x "$deb" / || exit 1; done; ldconfig' _ "$KIT"
    fi
    # NVIDIA's EGL vendor file, where glvnd does not find it by itself.
    if ! ls /usr/share/glvnd/egl_vendor.d/*nvidia* > /dev/null 2>&1 \
        && [ -f /usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json ]; then
        export __EGL_VENDOR_LIBRARY_FILENAMES=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
    fi
    if ! ldconfig -p | grep -q libEGL_nvidia && [ -d /usr/local/nvidia/lib64 ]; then
        export LD_LIBRARY_PATH="/usr/local/nvidia/lib64${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
    fi
    stage gl-setup 10 bash -c 'echo "__EGL_VENDOR_LIBRARY_FILENAMES=${__EGL_VENDOR_LIBRARY_FILENAMES:-}";
        echo "LD_LIBRARY_PATH=${LD_LIBRARY_PATH:-}"; ldconfig -p | grep -E "libEGL|libGL" || true'
    SITE="$WORK/site"
    stage install 120 "$PYTHON" -m pip install --no-index --no-deps --no-compile --disable-pip-version-check \
        --target "$SITE" "$KIT"/wheels/*.whl
    export PYTHONPATH="$SITE${PYTHONPATH:+:$PYTHONPATH}"
    stage nvidia-smi 30 nvidia-smi
    stage gpu 30 nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
else
    skip gl-libraries "--cpu"
    skip install "--cpu: $PYTHON's own marl-render"
    skip nvidia-smi "--cpu"
    skip gpu "--cpu"
fi
stage requirements 60 "$PYTHON" "$KIT/report.py" requirements
stage gl-info 60 "$PYTHON" -m marl_render.info --json
# shellcheck disable=SC2086  # TESTS is a list of paths
stage tests 180 "$PYTHON" -m pytest -q -p no:cacheprovider -o addopts= --junitxml "$WORK/tests.xml" $TESTS
if [ -n "$INTEROP_TESTS" ]; then
    # shellcheck disable=SC2086  # INTEROP_TESTS is a list of paths
    stage interop-tests 200 "$PYTHON" -m pytest -q -p no:cacheprovider -o addopts= -rs \
        --junitxml "$WORK/interop-tests.xml" $INTEROP_TESTS
else
    skip interop-tests "no interop tests given"
fi

bench_env() {  # bench_env TASK WORLDS [AGENTS]: every readback of READBACKS in one call, taking turns
    local name="env-$1-$2" agents=()
    if [ $# -gt 2 ]; then
        name="env-$1:$3-$2"
        agents=(--agents "$3")
    fi
    # shellcheck disable=SC2086  # READBACKS is a list of values
    stage "$name" 150 "$PYTHON" -m marl_render.bench env --env "$1" --worlds "$2" "${agents[@]}" --resolution 64 \
        --steps "$STEPS" --device "$DEVICE" --readback $READBACKS --json
}
PBR="$KIT/pybatchrender"
bench_pybatchrender() {  # bench_pybatchrender WORLDS: its CartPole, with the cuda.cudart alias (pbr_run.py)
    stage "pybatchrender-cartpole-$1" 120 env PYTHONPATH="$PBR${PYTHONPATH:+:$PYTHONPATH}" "$PYTHON" \
        "$KIT/pbr_run.py" "$PBR/examples/scripts/cartpole_benchmark.py" --num-scenes "$1" --tile-resolution 64 64 \
        --steps "$PBR_STEPS"
}
for worlds in $SIZES; do bench_env cartpole "$worlds"; done
if [ -f "$PBR/examples/scripts/cartpole_benchmark.py" ]; then
    for worlds in $SIZES; do bench_pybatchrender "$worlds"; done
else
    skip pybatchrender "no PyBatchRender clone in the kit"
fi
for worlds in $SIZES; do bench_env spread "$worlds" 4; done
# Once with the GL's debug output (MARL_RENDER_PRC, marl_render/backend.py): which call raises the
# GL errors 0x502 (invalid operation) that the H200 runs logged, and why.
FIRST_READBACK=${READBACKS%% *}
stage gl-debug 90 env MARL_RENDER_PRC='gl-debug #t\nnotify-level-glgsg warning' "$PYTHON" -m marl_render.bench env \
    --env spread --agents 4 --worlds "$GL_DEBUG_WORLDS" --resolution 64 --steps 3 --device "$DEVICE" \
    --readback "$FIRST_READBACK" --json
# shellcheck disable=SC2086  # RENDER_ARGS is a list of arguments
stage render 150 "$PYTHON" -m marl_render.bench render $RENDER_ARGS --json
# Several processes on one GPU (envs/multiprocess.py): the same rollout with all the worlds in this
# process, then over each count of worker processes, each with its own GL context on the device.
if [ -n "$PROCESSES" ]; then
    # shellcheck disable=SC2086  # PROCESSES is a list of values
    stage processes 150 "$PYTHON" -m marl_render.bench parallel --env cartpole --worlds "$PROCESSES_WORLDS" \
        --resolution 64 --steps "$STEPS" --repeats 3 --kinds single processes --processes $PROCESSES \
        --device "$DEVICE" --json
else
    skip processes "no process counts given"
fi

# Larger sizes while memory allows: a task stops at its first refusal (the memory guard) or failure.
for worlds in $MORE; do bench_env cartpole "$worlds" || break; done
if [ -f "$PBR/examples/scripts/cartpole_benchmark.py" ]; then
    for worlds in $MORE; do bench_pybatchrender "$worlds" || break; done
fi
for worlds in $MORE; do bench_env spread "$worlds" 4 || break; done

mkdir -p "$(dirname "$JSON")"
"$PYTHON" "$KIT/report.py" compose "$WORK" "$JSON" --mode "$MODE" --budget "$BUDGET" --started "$START" \
    || python3 "$KIT/report.py" compose "$WORK" "$JSON" --mode "$MODE" --budget "$BUDGET" --started "$START"
status=$?
echo "[check] $(($(date +%s) - START)) s; wrote $JSON" >&2
rm -rf "$WORK"
exit "$status"
