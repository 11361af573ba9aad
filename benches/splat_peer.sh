#!/usr/bin/env bash
# Sylva's trainer beside a peer's (Brush) on one COLMAP scene, back to back, several rounds.
#
#   benches/splat_peer.sh COLMAP_DIR [--peer PATH] [--steps N] [--resolution PX] [--rounds K]
#                         [--max-gaussians N] [--work DIR]
#
# COLMAP_DIR holds images/ and sparse/0 (or sparse/). --peer is the path of a peer trainer's
# binary with Brush's command line (`brush SOURCE --total-train-iters N --max-resolution PX
# --eval-split-every 8 --eval-every N --export-every N --export-path DIR --seed S`), built by
# hand from its public source in a scratch folder outside this repository; nothing here builds
# or fetches it. Without --peer, Sylva runs alone.
#
# Each round runs `sylva train --exposure off` (full-image held-out metrics, as the peer's) and
# then the peer with the same steps, longest image side, held-out split (every 8th image) and
# seed, under GNU time. The table gives per run the held-out PSNR and SSIM at the last step,
# the Gaussians at the end, wall seconds (loading included) and per step, Sylva's training-loop
# time per step, and the peak resident memory; then the means and the ratios Sylva / peer.
# Defaults: 500 steps at 320 px, 3 rounds, the peer's and Sylva's own default budgets.
#
# Environment: PROFILE (cargo profile of the sylva binary, default release), WGPU_BACKEND and
# XDG_RUNTIME_DIR (default vulkan and /tmp, for lavapipe), PYTHON (default python3).
set -euo pipefail

ROOT="$(cd "$(dirname "$0")/.." && pwd)"
PROFILE="${PROFILE:-release}"
PYTHON="${PYTHON:-python3}"
export WGPU_BACKEND="${WGPU_BACKEND:-vulkan}"
export XDG_RUNTIME_DIR="${XDG_RUNTIME_DIR:-/tmp}"

if [ $# -lt 1 ] || [ "${1#--}" != "$1" ]; then
    sed -n '2,19p' "$0" >&2
    exit 2
fi
COLMAP="$(cd "$1" && pwd)"
shift
WORK="$ROOT/target/bench-splat-peer"
ARGS=()
while [ $# -gt 0 ]; do
    case "$1" in
        --work) WORK="$2"; shift 2 ;;
        --peer|--steps|--resolution|--rounds|--max-gaussians) ARGS+=("$1" "$2"); shift 2 ;;
        *) echo "unknown argument $1" >&2; exit 2 ;;
    esac
done
command -v /usr/bin/time >/dev/null || { echo "needs GNU time (Debian package time)" >&2; exit 1; }

( cd "$ROOT" && cargo build --profile "$PROFILE" --quiet )
DIR="$PROFILE"
[ "$PROFILE" = dev ] && DIR=debug
[ "$PROFILE" = test ] && DIR=debug
SYLVA="$ROOT/target/$DIR/sylva"
rm -rf "$WORK"
mkdir -p "$WORK"
exec "$PYTHON" "$ROOT/benches/splat_peer.py" --colmap "$COLMAP" --sylva "$SYLVA" --work "$WORK" "${ARGS[@]}"
