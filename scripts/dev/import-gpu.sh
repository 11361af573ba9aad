#!/usr/bin/env bash
# One-off import of the GPU crates of the scratch workspace into src/splat/gpu and shaders/.
set -euo pipefail
src=/work/splat-dev
dst=/work/main/src/splat/gpu
root=/work/main
mkdir -p "$dst/loss" "$root/shaders/loss" "$root/tests/gpu"
for f in "$src"/gpu/src/*.rs; do
  b=$(basename "$f"); [ "$b" = lib.rs ] && b=mod.rs
  sed -e 's/\bcrate::/crate::splat::gpu::/g' -e 's/splat_core::/crate::splat::/g' \
      -e 's#"\.\./shaders/#"../../../shaders/#g' "$f" > "$dst/$b"
done
cp "$src"/gpu/shaders/*.wgsl "$root/shaders/"
for f in "$src"/gpuloss/src/*.rs; do
  b=$(basename "$f"); [ "$b" = lib.rs ] && b=mod.rs
  sed -e 's/\bcrate::/crate::splat::gpu::loss::/g' -e 's/splat_core::/crate::splat::/g' \
      -e 's/splat_cpu::/crate::splat::cpu::/g' \
      -e 's#"\.\./shaders/#"../../../../shaders/loss/#g' "$f" > "$dst/loss/$b"
done
cp "$src"/gpuloss/shaders/*.wgsl "$root/shaders/loss/"
for f in "$src"/gpu/tests/*.rs "$src"/gpu/tests/common/mod.rs; do
  b=$(basename "$f"); [ "$f" = "$src/gpu/tests/common/mod.rs" ] && b=common.rs
  sed -e 's/splat_gpu::/sylva::splat::gpu::/g' -e 's/splat_core::/sylva::splat::/g' \
      -e 's/splat_cpu::/sylva::splat::cpu::/g' -e 's/^mod common;$/use crate::common;/' "$f" > "$root/tests/gpu/$b"
done
