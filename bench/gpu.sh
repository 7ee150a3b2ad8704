#!/usr/bin/env bash
# The GPU checklist (docs/gpu.md) in one run, on a machine with an NVIDIA GPU, torch with CUDA and
# cubecloud importable; gsplat, if wanted, installed in its own folder so that both CUDA
# rasterizers get measured:
#
#   bash bench/gpu.sh OUT [GSPLAT_SITE] [SECONDS]
#
# 1. gsplat's CUDA kernels compile at its first import (a JIT build): started first, in the
#    background, on 12 cores;
# 2. meanwhile `pytest -m cuda` with the plain PyTorch rasterizer on the GPU;
# 3. once gsplat has built: `pytest -m cuda` again, with gsplat;
# 4. `bench/pipeline.py` (`cubecloud run --device cuda`, cold numba cache) for `fast` and
#    `balanced`, with gsplat, then `fast` with the PyTorch rasterizer;
# 5. the paper's CuNeRF on the GPU: seconds per iteration at 512³.
#
# Every step has a share of SECONDS (default 560) and is cut at the deadline; OUT/log.txt holds
# each step's output and time.
set -u
OUT=${1:?usage: bench/gpu.sh OUT [GSPLAT_SITE] [SECONDS]}
GSPLAT_SITE=${2:-}
DEADLINE=$(($(date +%s) + ${3:-560}))
PLAIN_PATH=${PYTHONPATH:-}
mkdir -p "$OUT"
exec > >(tee -a "$OUT/log.txt") 2>&1

step() { # step NAME MAX_SECONDS COMMAND...: run within the deadline, and say how long it took
	local name=$1 most=$2 left start
	shift 2
	left=$((DEADLINE - $(date +%s) - 5))
	if ((left < 20)); then
		echo "== $name: skipped, ${left}s left"
		return 1
	fi
	((most > left)) && most=$left
	echo "== $name (at most ${most}s): $*"
	start=$(date +%s%N)
	timeout "$most" "$@"
	local status=$?
	echo "== $name: exit $status after $((($(date +%s%N) - start) / 1000000)) ms"
	return $status
}

nvidia-smi --query-gpu=name,memory.total,driver_version,clocks.max.sm --format=csv
python3 -c "import torch, numba; print('torch', torch.__version__, 'CUDA', torch.version.cuda, torch.cuda.get_device_name(), '| numba', numba.__version__)"
nproc

built=no
if [[ -n $GSPLAT_SITE ]]; then
	(
		cd /tmp && start=$(date +%s)
		# No TORCH_CUDA_ARCH_LIST: torch re-runs ninja in each process that loads gsplat, and a
		# process whose arch flags differ from the build's rebuilds everything (docs/gpu.md).
		MAX_JOBS=12 PYTHONPATH="$GSPLAT_SITE:$PLAIN_PATH" timeout 420 \
			python3 -c "from gsplat.cuda._backend import _C; assert _C is not None; print('gsplat built')"
		echo "gsplat build exit $? after $(($(date +%s) - start)) s"
	) >"$OUT/gsplat_build.txt" 2>&1 &
	builder=$!
fi

step "pytest -m cuda, PyTorch rasterizer" 200 python3 -m pytest -q -s -m cuda tests/test_cuda.py -p no:cacheprovider

if [[ -n $GSPLAT_SITE ]]; then
	left=$((DEADLINE - $(date +%s) - 200))
	((left > 0)) && timeout "$left" tail --pid="$builder" -f /dev/null
	tail -n 20 "$OUT/gsplat_build.txt"
	if grep -q "gsplat built" "$OUT/gsplat_build.txt"; then
		built=yes
		export PYTHONPATH="$GSPLAT_SITE:$PLAIN_PATH"
		step "pytest -m cuda, gsplat" 150 python3 -m pytest -q -s -m cuda tests/test_cuda.py -p no:cacheprovider
	fi
fi

stages() { # what each stage of a (possibly cut) pipeline run took and scored, from its manifests
	python3 - "$1" <<'PY'
import json, sys
from pathlib import Path
for manifest in sorted(Path(sys.argv[1]).glob("*/manifest.json"), key=lambda p: p.stat().st_mtime):
    data = json.loads(manifest.read_text())
    metrics = data.get("metrics") or {}
    keep = ("psnr_3d", "train_seconds", "seconds_per_1000_iterations", "iterations_per_second", "test_psnr",
            "gaussians", "cunerf_vs_reference_psnr", "peak_gpu_mb", "peak_rss_mb")
    print(manifest.parent.name, data.get("timings_s", {}).get("total"), {k: metrics[k] for k in keep if k in metrics})
PY
}

pipeline() { # pipeline NAME MAX_SECONDS PRESET: one cold `cubecloud run --device cuda`, kept for its manifests
	rm -rf "/tmp/gpu-$3"
	step "$1" "$2" python3 bench/pipeline.py --preset "$3" --repeats 1 --keep "/tmp/gpu-$3" -- --device cuda
	stages "/tmp/gpu-$3"
}

pipeline "fast, --device cuda ($([[ $built == yes ]] && echo gsplat || echo PyTorch) rasterizer)" 200 fast
pipeline "balanced, --device cuda" 240 balanced
step "paper CuNeRF at 512³, 60 s of training" 170 \
	python3 bench/cunerf.py --models cunerf --preset paper --size 512 --seconds 60 --eval-every 30 --device cuda
if [[ $built == yes ]]; then
	export PYTHONPATH=$PLAIN_PATH
	pipeline "fast, --device cuda (PyTorch rasterizer)" 200 fast
fi
nvidia-smi --query-gpu=name,memory.used --format=csv
