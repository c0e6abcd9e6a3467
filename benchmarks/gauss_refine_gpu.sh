#!/usr/bin/env bash
# Issue 6's acceptance scene on the GPU: one fit at the issue's settings (saved), then the
# per-frame refinement variants on that fit (gauss_refine_check.py), then one end-to-end fit
# with the chosen refinement, timed. Run from the repository root after gpu_setup.sh.
#   bash benchmarks/gauss_refine_gpu.sh OUT_DIR [SEED] ['VARIANT_JSON'...]
set -e
out=$1
seed=${2:-0}
shift 2 || true
mkdir -p "$out"
G='"hull_resolution": 128, "max_init_gaussians": 12000, "iterations": 1500, "views_per_step": 4, "densify_until": 1100, "densify_grad": 5e-05, "lambda_hull": 0.01'
python3 benchmarks/gauss_reconstruct.py --scene-dir "$out/scene" --seed "$seed" --device cuda \
  --out "$out/fit.json" --save-reconstruction "$out/fit_recon" --options "{$G}" > "$out/fit.log" 2>&1
python3 benchmarks/gauss_refine_check.py --scene "$out/scene" --recon "$out/fit_recon" \
  --device cuda --options "{$G}" --out "$out/refine.json" --variants "$@" 2>&1 \
  | grep -v "^Module\|^Warp \|^   " | tee "$out/refine.log"
