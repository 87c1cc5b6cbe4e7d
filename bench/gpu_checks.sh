#!/usr/bin/env bash
# The checks that need a CUDA GPU, in one run: the CUDA cases of the clustering and CUDA-graph tests, then
# bench_inference.py on the GPU (fps single-frame and batched, with and without CUDA graphs; training steps).
#
#   bash bench/gpu_checks.sh OUT_DIR [WHEEL_DIR]
#
# Runs from the repository's root with the machine's own python3 (torch with CUDA), without installing the package:
# the stage folders are linked into a temporary ``selfseg`` package as pyproject.toml maps them. WHEEL_DIR: pure-Python
# wheels the machine lacks (trimesh, for the analytic test fixtures), installed into a temporary folder.
# Writes OUT_DIR/tests.log, OUT_DIR/inference_cuda.json and OUT_DIR/bench.log.
set -uo pipefail
out=${1:?usage: bench/gpu_checks.sh OUT_DIR [WHEEL_DIR]}
wheels=${2:-}
py=${PYTHON:-python3}
mkdir -p "$out"
pkg=$(mktemp -d)
mkdir "$pkg/selfseg"
for f in selfseg/*; do ln -s "$PWD/$f" "$pkg/selfseg/"; done
for d in generate method baselines eval; do ln -s "$PWD/$d" "$pkg/selfseg/$d"; done
if [[ -n $wheels ]]; then
    "$py" -m pip install -q --no-index --no-deps --no-compile --target "$pkg" "$wheels"/*.whl || exit 1
fi
export PYTHONPATH=$pkg PYTHONUNBUFFERED=1
nvidia-smi -L
"$py" -c 'import torch, sys; print(sys.version.split()[0], "torch", torch.__version__, torch.cuda.get_device_name(0))'
"$py" -m pytest -q -p no:cacheprovider tests/test_cuda_graphs.py tests/test_meanshift_torch.py 2>&1 | tee "$out/tests.log"
tests_rc=$?
"$py" bench/bench_inference.py --device cuda --threads 16 --repeats 20 --batch 64 --train-steps 20 \
    --out "$out/inference_cuda.json" 2>&1 | tee "$out/bench.log"
bench_rc=$?
echo "tests rc $tests_rc, bench rc $bench_rc"
exit $((tests_rc || bench_rc))
