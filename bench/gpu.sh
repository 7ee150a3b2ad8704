#!/usr/bin/env bash
# The GPU checklist (docs/gpu.md) in one run, on a machine with an NVIDIA GPU, torch with CUDA and
# cubecloud importable; gsplat, if wanted, installed in its own folder so that both CUDA
# rasterizers get measured:
#
#   bash bench/gpu.sh OUT [GSPLAT_SITE] [SECONDS]
#   STEPS="gsplat-tests fast paper-splat" bash bench/gpu.sh OUT GSPLAT_SITE   # only these steps
#
# 1. gsplat's CUDA kernels compile at its first import (a JIT build): started first, in the
#    background, on 12 cores;
# 2. meanwhile `pytest -m cuda` with the plain PyTorch rasterizer on the GPU;
# 3. once gsplat has built: `pytest -m cuda` again, with gsplat;
# 4. `bench/pipeline.py` (`cubecloud run --device cuda`, cold numba cache) for `fast` and
#    `balanced`, with gsplat, then `fast` with the PyTorch rasterizer;
# 5. the paper's CuNeRF on the GPU: seconds per iteration at 512³;
# 6. the paper's splat stage (30 000 iterations at 512²) on a paper-preset scene, prepared while
#    gsplat builds. Its field is the grid model for 2000 iterations: the splat's speed is the
#    figure, and the paper's MLP spends ~10 min on the H200 reconstructing 512³ (docs/gpu.md).
#
# 7. (issue 54, asked for by name) cunerf-precision: the paper's CuNeRF at 512³ to iteration
#    $STOP_AT (4000) of its schedule in float32, tf32 and bf16, each scored on 2^20 voxels and
#    timed baking 4 slices; then paper-cunerf-run: `cubecloud cunerf --preset paper` in the
#    fastest precision within 0.3 dB of float32 (or $PRECISION), cut at the deadline with its
#    checkpoint copied to OUT, and resumed from $CARRIED_CHECKPOINT when that file exists.
#
# STEPS picks among cuda-metrics, torch-tests, gsplat-tests, fast, balanced, paper-cunerf, paper-splat
# and fast-torch (default: all of them), and suite, cunerf-precision and paper-cunerf-run (asked for by name only): the whole test suite
# apart from the cuda tests, on 7 pytest-xdist workers of 2 threads each, as CI's 2 cores give
# each test (about 140 s on an H100 machine's 16 cores; docs/gpu.md, the fourth session). The paper's splat gets all the time left, and is cut
# (with its checkpoint saved) at the deadline.
#
# Every step has a share of SECONDS (default 560) and is cut at the deadline; OUT/log.txt holds
# each step's output and time.
set -u
OUT=${1:?usage: bench/gpu.sh OUT [GSPLAT_SITE] [SECONDS]}
GSPLAT_SITE=${2:-}
DEADLINE=$(($(date +%s) + ${3:-560}))
PLAIN_PATH=${PYTHONPATH:-}
STEPS=" ${STEPS:-cuda-metrics torch-tests gsplat-tests fast balanced paper-cunerf paper-splat fast-torch} "
wanted() { [[ $STEPS == *" $1 "* ]]; }
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
	# SIGINT first: a stage cut at the deadline saves its checkpoint and says how far it got.
	timeout -s INT -k 30 "$most" "$@"
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

PAPER=/tmp/gpu-paper
paper_scene() { # the paper preset's scene: 512³, the grid field for 2000 iterations, 60 slices at 512²
	rm -rf "$PAPER" && cubecloud preprocess -o "$PAPER" --preset paper -q &&
		cubecloud cunerf "$PAPER" --preset paper --model fast --iterations 2000 --device cuda -q &&
		cubecloud export "$PAPER" --preset paper --device cuda -q
}
wanted paper-splat && step "paper scene (while gsplat builds; not timed)" 240 bash -c "$(declare -f paper_scene); PAPER=$PAPER paper_scene" && stages "$PAPER"
wanted cuda-metrics && step "pytest -m cuda, the metrics on the GPU" 60 python3 -m pytest -q -s -m cuda tests/test_cuda.py -k volume_ssim -p no:cacheprovider
wanted suite && NUMBA_NUM_THREADS=2 OMP_NUM_THREADS=2 step "the whole suite but -m cuda, a GPU in sight" 300 \
	python3 -m pytest -q -n 7 -m "not cuda" -p no:cacheprovider -rfEs
wanted torch-tests && step "pytest -m cuda, PyTorch rasterizer" 200 python3 -m pytest -q -s -m cuda tests/test_cuda.py -p no:cacheprovider

if [[ -n $GSPLAT_SITE ]]; then
	left=$((DEADLINE - $(date +%s) - 200))
	((left > 0)) && timeout "$left" tail --pid="$builder" -f /dev/null
	tail -n 20 "$OUT/gsplat_build.txt"
	if grep -q "gsplat built" "$OUT/gsplat_build.txt"; then
		built=yes
		export PYTHONPATH="$GSPLAT_SITE:$PLAIN_PATH"
		wanted gsplat-tests && step "pytest -m cuda, gsplat" 150 python3 -m pytest -q -s -m cuda tests/test_cuda.py -p no:cacheprovider
	fi
fi


pipeline() { # pipeline NAME MAX_SECONDS PRESET: one cold `cubecloud run --device cuda`, kept for its manifests
	rm -rf "/tmp/gpu-$3"
	step "$1" "$2" python3 bench/pipeline.py --preset "$3" --repeats 1 --keep "/tmp/gpu-$3" -- --device cuda
	stages "/tmp/gpu-$3"
}

wanted fast && pipeline "fast, --device cuda ($([[ $built == yes ]] && echo gsplat || echo PyTorch) rasterizer)" 200 fast
wanted balanced && pipeline "balanced, --device cuda" 240 balanced
wanted paper-cunerf && step "paper CuNeRF at 512³, 60 s of training" 170 \
	python3 bench/cunerf.py --models cunerf --preset paper --size 512 --seconds 60 --eval-every 30 --device cuda
if wanted paper-splat && [[ -f $PAPER/export/manifest.json ]]; then
	# Progress is drawn only on a terminal: script(1) gives it one, and the log keeps the rate.
	export COLUMNS=200
	# All the time left: script(1) does not pass SIGINT on, so the cut is made inside it.
	left=$((DEADLINE - $(date +%s) - 40))
	if ((left < 20)); then # timeout(1) would take 0 or less as no limit
		echo "== paper splat: skipped, ${left}s left"
	else
		step "paper splat, 30 000 iterations at 512²" $((left + 30)) \
			script -qfec "timeout -s INT -k 20 $left cubecloud splat $PAPER --preset paper --device cuda" "$OUT/paper_splat.tty"
	fi
	[[ -f $OUT/paper_splat.tty ]] && tr '\r' '\n' <"$OUT/paper_splat.tty" | sed 's/\x1b\[[0-9;]*[A-Za-z]//g' | grep -a "it/s" | awk 'NR % 50 == 0' | tail -n 40
	stages "$PAPER"
fi
MLP=/tmp/gpu-paper-mlp
if wanted cunerf-precision || wanted paper-cunerf-run; then
	[[ -f $MLP/preprocess/manifest.json ]] || step "paper volume, 512³ (not timed)" 150 cubecloud preprocess -o "$MLP" --preset paper -q
fi
if wanted cunerf-precision; then
	for precision in float32 tf32 bf16; do
		step "paper CuNeRF at 512³ to iteration ${STOP_AT:-4000}, $precision" 200 \
			python3 bench/cunerf.py --models cunerf --preset paper --size 512 --work "$MLP" --stop-at "${STOP_AT:-4000}" \
			--seconds 1e9 --eval-every 1e9 --points 1048576 --precision $precision --bake-slices 4 --profile-steps 20 --device cuda |
			tee "$OUT/precision_$precision.txt"
	done
	# The fastest precision whose 3D PSNR estimate is within 0.3 dB of float32's at the same iteration.
	PRECISION=${PRECISION:-$(python3 - "$OUT" <<'PY'
import json, sys
from pathlib import Path
runs = {}
for path in Path(sys.argv[1]).glob("precision_*.txt"):
    lines = path.read_text().splitlines()
    points = [l.split() for l in lines if l.strip() and l.split()[0].isdigit()]
    summary = [json.loads(l.split(":", 1)[1]) for l in lines if l.startswith("summary:")]
    if points and summary:
        runs[summary[0]["precision"]] = (float(points[-1][3]), summary[0]["s_per_1000"])
best = "float32"
if "float32" in runs:
    good = [p for p, (score, _) in runs.items() if score >= runs["float32"][0] - 0.3]
    best = min(good, key=lambda p: runs[p][1])
print(best)
PY
)}
	echo "== chosen precision: $PRECISION"
fi
if wanted paper-cunerf-run; then
	resume=""
	if [[ -f ${CARRIED_CHECKPOINT:-/nonexistent} ]]; then
		mkdir -p "$MLP/.cunerf.partial" && cp "$CARRIED_CHECKPOINT" "$MLP/.cunerf.partial/checkpoint.pt" && resume=--resume
	fi
	export COLUMNS=200
	left=$((DEADLINE - $(date +%s) - 40))
	if ((left < 20)); then
		echo "== paper CuNeRF run: skipped, ${left}s left"
	else
		step "paper CuNeRF, 200 000 iterations, ${PRECISION:-bf16} $resume" $((left + 30)) \
			script -qfec "timeout -s INT -k 20 $left cubecloud cunerf $MLP --preset paper --precision ${PRECISION:-bf16} --device cuda $resume" "$OUT/paper_cunerf.tty"
	fi
	[[ -f $OUT/paper_cunerf.tty ]] && tr '\r' '\n' <"$OUT/paper_cunerf.tty" | sed 's/\x1b\[[0-9;]*[A-Za-z]//g' | grep -a "it/s" | awk 'NR % 400 == 0' | tail -n 30
	cp "$MLP/.cunerf.partial/checkpoint.pt" "$OUT/paper_cunerf_checkpoint.pt" 2>/dev/null
	python3 - "$MLP" <<'PY'
import json, sys, torch
from pathlib import Path
work = Path(sys.argv[1])
manifest = work / "cunerf" / "manifest.json"
if manifest.exists():
    data = json.loads(manifest.read_text())
    print("complete:", json.dumps({"timings_s": data.get("timings_s"), "metrics": data.get("metrics")}))
checkpoint = work / ".cunerf.partial" / "checkpoint.pt"
if checkpoint.exists():
    state = torch.load(checkpoint, weights_only=False, map_location="cpu")
    print("checkpoint: iteration", state["iteration"], "training seconds", round(state["elapsed_s"], 1))
    for row in state["history"][:: max(1, len(state["history"]) // 25)] + state["history"][-1:]:
        print(json.dumps(row))
PY
fi
if wanted fast-torch && [[ $built == yes ]]; then
	export PYTHONPATH=$PLAIN_PATH
	pipeline "fast, --device cuda (PyTorch rasterizer)" 200 fast
fi
nvidia-smi --query-gpu=name,memory.used --format=csv
