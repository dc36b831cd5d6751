#!/usr/bin/env bash
# The CUDA path checked on a GPU machine: tests/test_device.py on every device the machine has
# (cpu and cuda): tiny real runs of recipes/es_td3.py with device=cuda (TD3, its optimisers and the
# buffers on the GPU, the ES mean on CPU, read from the checkpoint), exact resume of a run killed
# mid-episode, every learner (td3, ddpg, sac) and the ERL and CEM-RL recipes, a run refused on
# another device than it was written on, and one TD3 update (fast and reference pieces) on the
# GPU against the CPU reference to float32 rounding.
#
#   OUT=<records folder> bash scripts/device_check.sh     # from the repository root
#
# The packages the machine lacks are installed from the wheels in .whl/ (if that folder exists)
# into $SITE (default /tmp/site), ahead of the checkout on PYTHONPATH; torch and numpy are the
# machine's own. $PYTHON (default python3) runs everything; $WORKERS (default 8) pytest workers,
# $TEST_TIMEOUT (default 200) seconds a test at most.
# Records in $OUT: log.txt (everything printed, written as it goes), versions.txt (GPU, CPU,
# Python and package versions) and device_tests.xml (pytest's JUnit report).
# Exit status: pytest's (0: every test passed); 3 where the wheels did not install.
set -u -o pipefail
OUT=${OUT:?set OUT to the folder the records go to}
PYTHON=${PYTHON:-python3}
SITE=${SITE:-/tmp/site}
WORKERS=${WORKERS:-8}
TEST_TIMEOUT=${TEST_TIMEOUT:-200}
mkdir -p "$OUT"

versions() {
    echo "date: $(date -u +%Y-%m-%dT%H:%M:%SZ)"
    echo "commit: $(git rev-parse HEAD 2>/dev/null || echo unknown)"
    echo "gpu: $(nvidia-smi -L 2>/dev/null | tr '\n' ';' || true)"
    echo "cpu: $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2- | sed 's/^ *//'), $(nproc) cores"
    "$PYTHON" - <<'EOF'
import platform
import torch, torchrl, tensordict, gymnasium, mujoco, hydra
print("python:", platform.python_version())
print("torch:", torch.__version__, "cuda", torch.version.cuda, "available", torch.cuda.is_available(),
      torch.cuda.get_device_name(0) if torch.cuda.is_available() else "")
print("torchrl:", torchrl.__version__, "tensordict:", tensordict.__version__, "gymnasium:", gymnasium.__version__,
      "mujoco:", mujoco.__version__, "hydra:", hydra.__version__)
try:
    import torchrl._torchrl  # noqa: F401
    print("torchrl C++ extension: loads")
except ImportError as error:
    print("torchrl C++ extension: does not load (", str(error)[:120], ")")
EOF
}

check() {
    if [ -d .whl ]; then
        "$PYTHON" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target "$SITE" .whl/*.whl || return 3
        export PYTHONPATH="$SITE:$PWD"
    else
        echo "no .whl/ folder: the packages of $PYTHON as they are"
        export PYTHONPATH="$PWD"
    fi
    versions | tee "$OUT/versions.txt"
    "$PYTHON" -m pytest -q -p no:cacheprovider -n "$WORKERS" --timeout "$TEST_TIMEOUT" --durations 20 \
        tests/test_device.py --junitxml "$OUT/device_tests.xml"
}

check 2>&1 | tee "$OUT/log.txt"
