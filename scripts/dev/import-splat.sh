#!/usr/bin/env bash
# One-off import of the splatting scratch workspace (/work/splat-dev) into src/splat.
set -euo pipefail
src=/work/splat-dev
dst=/work/main/src/splat
mkdir -p "$dst"
cp "$src/core/src/model.rs" "$src/core/src/camera.rs" "$dst/"
for f in "$src"/train/src/*.rs; do
  b=$(basename "$f")
  [ "$b" = lib.rs ] && continue
  [ "$b" = knn.rs ] && continue
  cp "$f" "$dst/$b"
done
sed -i -e 's/splat_core::/crate::splat::/g' -e 's/\bcrate::\(adam\|camera_models\|cameras\|config\|eval\|export\|export_splat\|init\|knn\|packed_image\|plot\|rng\|strategy\)\b/crate::splat::\1/g' "$dst"/*.rs
# The CPU reference.
mkdir -p "$dst/cpu"
for f in "$src"/cpu/src/*.rs; do
  b=$(basename "$f"); [ "$b" = lib.rs ] && b=mod.rs
  sed -e 's/\bcrate::/crate::splat::cpu::/g' -e 's/splat_core::/crate::splat::/g' "$f" > "$dst/cpu/$b"
done
