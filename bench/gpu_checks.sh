#!/usr/bin/env bash
# The checks that need a CUDA GPU, in one run: the CUDA cases of the clustering and CUDA-graph tests, then
# bench_inference.py on the GPU (fps single-frame and batched, with and without CUDA graphs; training steps).
#
#   [PARTS=inference,training] bash bench/gpu_checks.sh OUT_DIR [WHEEL_DIR]
#
# Runs from the repository's root with the machine's own python3 (torch with CUDA), without installing the package:
# the stage folders are linked into a temporary ``selfseg`` package as pyproject.toml maps them. WHEEL_DIR: pure-Python
# wheels the machine lacks (trimesh, for the analytic test fixtures), installed into a temporary folder. The analytic
# test scenes need open3d; where it is missing, make them here first and carry them:
#   .venv/bin/python -c "from selfseg.analytic import *; make_dataset(__import__('pathlib').Path('DIR'), two_box_scenes())"
# and run with SELFSEG_ANALYTIC_DATASET=DIR.
# METHOD_CONFIGS="YAML ...": time the network as each of those embedding-method config files runs it
# (bench_inference.py --method-config) instead of the two network presets.
# Writes OUT_DIR/tests.log, OUT_DIR/inference_cuda.json, OUT_DIR/training_cuda.json (PARTS without "training": not
# timed) and OUT_DIR/bench.log.
set -uo pipefail
out=${1:?usage: bench/gpu_checks.sh OUT_DIR [WHEEL_DIR]}
wheels=${2:-}
py=${PYTHON:-python3}
nets=(); for spec in ${METHOD_CONFIGS:-}; do nets+=(--method-config "$spec"); done
mkdir -p "$out"
pkg=$(mktemp -d)
mkdir "$pkg/selfseg"
for f in selfseg/*; do ln -s "$PWD/$f" "$pkg/selfseg/"; done
for d in generate method baselines eval; do ln -s "$PWD/$d" "$pkg/selfseg/$d"; done
if [[ -n $wheels ]]; then
    "$py" -m pip install -q --no-index --no-deps --no-compile --target "$pkg" "$wheels"/*.whl || exit 1
fi
export PYTHONPATH=$pkg PYTHONUNBUFFERED=1
# The analytic test scenes are ray-cast with open3d; without it, a copy made elsewhere (SELFSEG_ANALYTIC_DATASET).
if ! "$py" -c 'import open3d' 2>/dev/null && [[ -z ${SELFSEG_ANALYTIC_DATASET:-} ]]; then
    echo "no open3d here: set SELFSEG_ANALYTIC_DATASET to a copy of the analytic test dataset" >&2
fi
nvidia-smi -L
"$py" -c 'import torch, sys; print(sys.version.split()[0], "torch", torch.__version__, torch.cuda.get_device_name(0))'
"$py" -P -m pytest -q -p no:cacheprovider --tb=short tests/test_cuda_graphs.py tests/test_meanshift_torch.py 2>&1 \
    | tee "$out/tests.log"
tests_rc=$?
# Inference on one CPU thread (host work of a frame is small; on 16 threads OpenCV's and torch's thread pools cost
# more than they save), training on 16 (its augmentation runs on the CPU).
"$py" bench/bench_inference.py --device cuda --threads 1 --repeats 20 --batch 64 --parts inference "${nets[@]}" \
    --out "$out/inference_cuda.json" 2>&1 | tee "$out/bench.log"
bench_rc=$?
if [[ ${PARTS:-inference,training} == *training* ]]; then
    "$py" bench/bench_inference.py --device cuda --threads 16 --train-steps 20 --parts training "${nets[@]}" \
        --out "$out/training_cuda.json" 2>&1 | tee -a "$out/bench.log"
    bench_rc=$((bench_rc || $?))
fi
echo "tests rc $tests_rc, bench rc $bench_rc"
exit $((tests_rc || bench_rc))
