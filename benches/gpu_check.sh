#!/usr/bin/env bash
# The GPU check of issue 41, for whoever has a GPU: Sylva's trainer on a plot of the paper's
# plot-3 size (857 photos at 1920×1080, `sylva synth --preset paper`), under the memory plan of
# an 8 GB card by default. It prints, as Markdown tables (docs/results/splatting.md, "GPU check"):
#   - steps/s at 1 M and 3 M Gaussians at 1920×1080 (`sylva bench train`, each phase timed);
#   - the GPU memory the plan allows against the most the device's allocator held;
#   - the held-out PSNR (every 8th photo) after a fixed number of steps from 1 M Gaussians;
#   - the NeRF baseline of issue 44 on the GPU (`sylva bench method`'s `nerf` arm at the paper's
#     settings on `tiny` seed 1, beside vanilla 3DGS, for GPU_CHECK_NERF_SECONDS each), after
#     its kernels' twin tests on this GPU (`cargo test --test gpu nerf`).
# The Gaussians start from the SfM points spread into jittered copies (`splat::start::spread_to`):
# the check measures the trainer, so it skips the LiDAR stages, and the plot's LiDAR is cut to
# 1 M points (GPU_CHECK_LIDAR_POINTS) to save its minutes.
#
# Usage: benches/gpu_check.sh [WORK_DIR]   (default: target/gpu-check; the plot is kept there
# and reused by the next run). Takes under 10 minutes on a 16-core machine with a GPU once
# Sylva is built (a cold release build takes a few minutes more).
#
# Settings (environment):
#   SYLVA_BIN              the sylva binary (default: build target/release/sylva)
#   GPU_CHECK_IMAGES       photos (857)            GPU_CHECK_WIDTH, _HEIGHT  photo size (1920, 1080)
#   GPU_CHECK_RESOLUTION   training's longest side (1920)
#   GPU_CHECK_GAUSSIANS    speed rows (1000000,3000000)   GPU_CHECK_STEPS  timed steps (200)
#   GPU_CHECK_PSNR_GAUSSIANS, GPU_CHECK_PSNR_STEPS  the held-out run (1000000, 2000)
#   GPU_CHECK_MEMORY_MB    the memory plan (8192: the paper's RTX 4060; 0 = the device's own)
#   GPU_CHECK_LIDAR_POINTS the plot's LiDAR points (1000000)
#   GPU_CHECK_NERF_SECONDS the NeRF's training time (120; 0 skips the NeRF section)
set -euo pipefail
cd "$(dirname "$0")/.."

work="${1:-target/gpu-check}"
images="${GPU_CHECK_IMAGES:-857}"
width="${GPU_CHECK_WIDTH:-1920}"
height="${GPU_CHECK_HEIGHT:-1080}"
resolution="${GPU_CHECK_RESOLUTION:-1920}"
gaussians="${GPU_CHECK_GAUSSIANS:-1000000,3000000}"
steps="${GPU_CHECK_STEPS:-200}"
psnr_gaussians="${GPU_CHECK_PSNR_GAUSSIANS:-1000000}"
psnr_steps="${GPU_CHECK_PSNR_STEPS:-2000}"
memory="${GPU_CHECK_MEMORY_MB:-8192}"
lidar="${GPU_CHECK_LIDAR_POINTS:-1000000}"
nerf_seconds="${GPU_CHECK_NERF_SECONDS:-120}"
export WGPU_BACKEND="${WGPU_BACKEND:-vulkan}"

if [ -z "${SYLVA_BIN:-}" ]; then
  cargo build --release --bin sylva
  SYLVA_BIN=target/release/sylva
fi
mkdir -p "$work"
plot="$work/plot-${images}x${width}x${height}"

echo "# Sylva GPU check, $(date -u +%Y-%m-%dT%H:%MZ)"
echo
echo "- sylva: $("$SYLVA_BIN" --version 2>/dev/null || echo unknown), commit $(git rev-parse --short HEAD 2>/dev/null || echo unknown)"
if command -v nvidia-smi >/dev/null 2>&1; then
  echo "- GPU: $(nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader)"
fi
echo "- CPU: $(nproc) cores; plot: $images photos at ${width}×${height}, trained at ${resolution} px; memory plan: ${memory} MiB (0 = the device's)"
echo

if [ ! -f "$plot/truth.json" ]; then
  start=$(date +%s)
  "$SYLVA_BIN" synth --preset paper --seed 1 --out "$plot" --images "$images" \
    --width "$width" --height "$height" --lidar-points "$lidar" >/dev/null
  echo "- plot generated in $(( $(date +%s) - start )) s"
  echo
fi

echo "## Speed and memory ($steps steps each, no densification)"
echo
"$SYLVA_BIN" bench train --colmap "$plot/colmap" --resolution "$resolution" \
  --gaussians "$gaussians" --steps "$steps" --gpu-memory-mb "$memory"
echo
echo "## Held-out PSNR after $psnr_steps steps from $psnr_gaussians Gaussians"
echo
"$SYLVA_BIN" bench train --colmap "$plot/colmap" --resolution "$resolution" \
  --gaussians "$psnr_gaussians" --steps "$psnr_steps" --gpu-memory-mb "$memory" --heldout
if command -v nvidia-smi >/dev/null 2>&1; then
  echo
  echo "- GPU memory in use now (driver): $(nvidia-smi --query-gpu=memory.used --format=csv,noheader)"
fi
if [ "$nerf_seconds" != "0" ]; then
  echo
  echo "## The NeRF baseline on this GPU (issue 44)"
  echo
  echo "Kernels against their CPU twin:"
  cargo test --test gpu nerf 2>&1 | grep -E "^test |test result" || true
  echo
  "$SYLVA_BIN" bench method --method-preset tiny --method-seeds 1 --method-arms vanilla,nerf \
    --method-nerf-device gpu --method-nerf-seconds "$nerf_seconds" --method-work "$work/nerf"
fi
