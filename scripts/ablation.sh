#!/usr/bin/env bash
# The paper's Table 5 ablation on a generated plot with known truth: vanilla 3DGS (SfM
# initialisation, no semantic term), LiDAR initialisation alone, and the full method (LiDAR
# initialisation + L_geo), each for the same number of steps; prints one table.
#
#   scripts/ablation.sh [PRESET] [STEPS] [RESOLUTION] [SEED]     (defaults: tiny 1000 80 1)
#
# Uses target/release/sylva (cargo build --release) or $SYLVA_BIN; work goes under
# $ABLATION_DIR (default target/ablation). Trains on the GPU (WGPU_BACKEND picks the API).
set -euo pipefail
cd "$(dirname "$0")/.."
preset="${1:-tiny}"
steps="${2:-1000}"
res="${3:-80}"
seed="${4:-1}"
bin="${SYLVA_BIN:-target/release/sylva}"
work="${ABLATION_DIR:-target/ablation}/$preset-$seed"
if [ ! -x "$bin" ]; then
  echo "no $bin: run cargo build --release first (or set SYLVA_BIN)" >&2
  exit 2
fi
if [ ! -f "$work/plot/truth.json" ]; then
  "$bin" synth --preset "$preset" --seed "$seed" --out "$work/plot"
fi
outs=()
for variant in "sfm off" "lidar off" "lidar paper" "lidar bind"; do
  set -- $variant
  out="$work/$1-semantic-$2-$steps-$res"
  outs+=("$out")
  if [ ! -f "$out/results.json" ]; then
    "$bin" run --lidar "$work/plot/lidar.laz" --colmap "$work/plot/colmap" \
      --control-points "$work/plot/control_points.csv" --field-dbh "$work/plot/field_dbh.csv" \
      --init "$1" --semantic "$2" --steps "$steps" --resolution "$res" --out "$out"
  fi
done
python3 - "$preset" "$steps" "$res" "${outs[@]}" <<'PY'
import json, sys
preset, steps, res, outs = sys.argv[1], sys.argv[2], sys.argv[3], sys.argv[4:]
names = ["vanilla 3DGS (SfM init)", "LiDAR init", "LiDAR init + L_geo"]
def f(v, d=2):
    return "n/a" if v is None else f"{v:.{d}f}"
print(f"{preset}, {steps} steps at {res} px")
print("| variant | PSNR (dB) | SSIM | DBH RMSE GS (cm) | DBH RMSE LiDAR (cm) | trunk dev (mm) | Gaussians | s |")
print("|---|---|---|---|---|---|---|---|")
for name, out in zip(names, outs):
    r = json.load(open(f"{out}/results.json"))
    t, d = r.get("train", {}), r.get("dbh", {})
    print(f"| {name} | {f(r['render']['psnr'])} | {f(r['render']['ssim'], 3)} | "
          f"{f(d.get('rmse_gs_cm'))} | {f(d.get('rmse_lidar_cm'))} | {f(d.get('trunk_radial_dev_mm'), 1)} | "
          f"{t.get('gaussians', {}).get('final')} | {f(t.get('seconds'), 0)} |")
PY
