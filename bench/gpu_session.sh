#!/usr/bin/env bash
# One device session's GPU checks (run by the lead through the device tool; not part of CI):
# the CUDA-only tests, gsplat 1.5.3 (JIT-compiled for sm_90) parity against the compiled CPU rasterizer,
# the rasterizer and frontend timings on the GPU. Wheels for gsplat and plyfile travel in .whl/ (bench/gpu_wheels.sh).
# Usage: bash bench/gpu_session.sh OUT_DIR
set -u
out=${1:-/tmp/gpu_out}; mkdir -p "$out"
log="$out/gpu.log"
exec > >(tee "$log") 2>&1
export PYTHONUNBUFFERED=1 TORCH_CUDA_ARCH_LIST=9.0 MAX_JOBS=14
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl
export PYTHONPATH=/tmp/site:$PWD
date -u; nvidia-smi -L; nproc; python3 -c "import torch; print('torch', torch.__version__, torch.version.cuda)"
nvcc --version | tail -2
( timeout 330 python3 -c "import time; t=time.time(); import gsplat; from gsplat.cuda._backend import _C; print('gsplat built', _C is not None, round(time.time()-t,1), 's')" > "$out/gsplat_build.log" 2>&1; echo "build rc $?" >> "$out/gsplat_build.log" ) &
build=$!
echo "== CUDA tests of the frontend"
timeout 120 python3 -m pytest -q -p no:cacheprovider -m gpu tests/frontend/test_model.py 2>&1 | tail -4
echo "== frontend timings (tiny on CPU, 4 threads; paper on the GPU)"
timeout 150 python3 -m bench frontend -- --configs tiny --threads 4 --iters 20
wait $build; tail -5 "$out/gsplat_build.log"
echo "== gsplat parity tests"
timeout 120 python3 -m pytest -q -p no:cacheprovider tests/mapping/test_rasterize_gsplat.py 2>&1 | tail -6
echo "== hole closing with the map on CUDA"
timeout 120 python3 -m pytest -q -p no:cacheprovider -m gpu tests/mapping/test_hole_closing.py 2>&1 | tail -4
echo "== rasterizer timings (cpu = compiled kernels on 4 threads of this machine's CPU; gsplat on the GPU)"
timeout 150 python3 -m bench render -- --device cuda --threads 4 --no-reference --repeats 10
echo "== map refinement, 20 iterations per keyframe at 320x240, then a 200-iteration final pass:"
echo "   GPU (gsplat) then this machine's CPU, 4 threads"
timeout 100 python3 -m bench refine -- --device cuda --keyframes 6 --final 200
timeout 150 python3 -m bench refine -- --device cpu --threads 4 --keyframes 6 --final 200
date -u
