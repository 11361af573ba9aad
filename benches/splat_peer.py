"""Sylva's trainer beside a peer's, on one COLMAP scene, back to back (see splat_peer.sh).

Each round runs `sylva train` and then, when given, the peer binary (Brush's CLI, built by hand
from its public source outside this repository) with the same scene, steps, longest image side,
held-out split (every 8th image) and seed, under GNU time for the peak memory. Per run it reads:

- Sylva: the summary line of `sylva train` (held-out PSNR and SSIM, Gaussians at the end, the
  training loop's steps/s);
- the peer: its last "Eval iter N: PSNR x, ssim y" line, and the vertex count of the PLY it
  exports at the last step;
- both: wall seconds of the whole command (loading included) and peak resident memory.

It prints one table row per run, then the means per trainer and the ratios Sylva / peer.
"""

import argparse
import glob
import os
import re
import statistics
import subprocess
import sys
import time

SYLVA_LINE = re.compile(
    r"held-out PSNR ([0-9.]+) dB, SSIM ([0-9.]+) over (\d+) views.*?; (\d+) Gaussians; ([0-9.]+) steps/s"
)
PEER_EVAL = re.compile(r"Eval iter (\d+): PSNR ([0-9.]+), ssim ([0-9.]+)")
MAX_RSS = re.compile(r"Maximum resident set size \(kbytes\): (\d+)")


def timed(cmd, env=None):
    """Runs cmd under GNU time -v; returns (wall s, peak RSS MiB, combined output)."""
    start = time.monotonic()
    p = subprocess.run(
        ["/usr/bin/time", "-v", *cmd],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=env,
    )
    wall = time.monotonic() - start
    out = p.stdout
    if p.returncode != 0:
        sys.exit(f"failed ({p.returncode}): {' '.join(cmd)}\n{out[-3000:]}")
    rss = MAX_RSS.search(out)
    return wall, (int(rss.group(1)) / 1024.0 if rss else float("nan")), out


def ply_vertices(folder):
    """Vertex count of the newest PLY under folder."""
    files = sorted(glob.glob(os.path.join(folder, "**", "*.ply"), recursive=True), key=os.path.getmtime)
    if not files:
        return None
    with open(files[-1], "rb") as f:
        for raw in f:
            line = raw.decode("ascii", "replace").strip()
            if line.startswith("element vertex"):
                return int(line.split()[-1])
            if line == "end_header":
                break
    return None


def run_sylva(a, work, rnd):
    out = os.path.join(work, f"sylva-{rnd}")
    cmd = [
        a.sylva, "train", "--colmap", a.colmap, "--out", out,
        "--steps", str(a.steps), "--resolution", str(a.resolution),
        "--seed", str(rnd), "--exposure", "off",
    ]
    if a.max_gaussians:
        cmd += ["--max-gaussians", str(a.max_gaussians)]
    wall, rss, text = timed(cmd)
    m = SYLVA_LINE.search(text)
    if not m:
        sys.exit(f"no summary line from sylva train:\n{text[-3000:]}")
    return {
        "trainer": "sylva",
        "psnr": float(m.group(1)),
        "ssim": float(m.group(2)),
        "views": int(m.group(3)),
        "gaussians": int(m.group(4)),
        "loop_s_per_step": 1.0 / float(m.group(5)),
        "wall": wall,
        "rss": rss,
    }


def run_peer(a, work, rnd):
    out = os.path.join(work, f"peer-{rnd}")
    os.makedirs(out, exist_ok=True)
    cmd = [
        a.peer, a.colmap, "--total-train-iters", str(a.steps),
        "--max-resolution", str(a.resolution), "--eval-split-every", str(a.test_every),
        "--eval-every", str(a.steps), "--export-every", str(a.steps),
        "--export-path", out, "--seed", str(rnd),
    ]
    if a.max_gaussians:
        cmd += ["--max-splats", str(a.max_gaussians)]
    env = dict(os.environ, RUST_LOG=os.environ.get("RUST_LOG", "info"))
    wall, rss, text = timed(cmd, env)
    evals = PEER_EVAL.findall(text)
    if not evals:
        sys.exit(f"no 'Eval iter' line from the peer:\n{text[-3000:]}")
    _, psnr, ssim = evals[-1]
    return {
        "trainer": "peer",
        "psnr": float(psnr),
        "ssim": float(ssim),
        "views": None,
        "gaussians": ply_vertices(out),
        "loop_s_per_step": None,
        "wall": wall,
        "rss": rss,
    }


def fmt(v, spec):
    return "n/a" if v is None else format(v, spec)


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--colmap", required=True)
    p.add_argument("--sylva", required=True)
    p.add_argument("--peer")
    p.add_argument("--steps", type=int, default=500)
    p.add_argument("--resolution", type=int, default=320)
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--test-every", type=int, default=8)
    p.add_argument("--max-gaussians", type=int, default=0)
    p.add_argument("--work", required=True)
    a = p.parse_args()
    os.makedirs(a.work, exist_ok=True)
    print(
        f"\n{a.colmap}: {a.steps} steps, longest side {a.resolution} px, every "
        f"{a.test_every}th image held out, {a.rounds} rounds, load {os.getloadavg()[0]:.2f}\n"
    )
    print("| round | trainer | PSNR dB | SSIM | Gaussians | wall s | wall s/step | loop s/step | peak MiB |")
    print("|---|---|---|---|---|---|---|---|---|")
    rows = []
    for rnd in range(1, a.rounds + 1):
        runs = [run_sylva(a, a.work, rnd)]
        if a.peer:
            runs.append(run_peer(a, a.work, rnd))
        for r in runs:
            rows.append(r)
            print(
                f"| {rnd} | {r['trainer']} | {r['psnr']:.2f} | {r['ssim']:.3f} | "
                f"{fmt(r['gaussians'], 'd')} | {r['wall']:.1f} | {r['wall'] / a.steps:.3f} | "
                f"{fmt(r['loop_s_per_step'], '.3f')} | {r['rss']:.0f} |",
                flush=True,
            )
    print("\n| trainer | PSNR dB | SSIM | Gaussians | wall s/step | peak MiB |")
    print("|---|---|---|---|---|---|")
    means = {}
    for t in ["sylva", "peer"]:
        rs = [r for r in rows if r["trainer"] == t]
        if not rs:
            continue
        g = [r["gaussians"] for r in rs if r["gaussians"] is not None]
        means[t] = {
            "psnr": statistics.mean(r["psnr"] for r in rs),
            "ssim": statistics.mean(r["ssim"] for r in rs),
            "gaussians": statistics.mean(g) if g else None,
            "step": statistics.mean(r["wall"] / a.steps for r in rs),
            "rss": statistics.mean(r["rss"] for r in rs),
        }
        m = means[t]
        print(
            f"| {t} | {m['psnr']:.2f} | {m['ssim']:.3f} | {fmt(m['gaussians'], '.0f')} | "
            f"{m['step']:.3f} | {m['rss']:.0f} |"
        )
    if "peer" in means:
        s, q = means["sylva"], means["peer"]
        print(
            f"\nsylva − peer: {s['psnr'] - q['psnr']:+.2f} dB PSNR, {s['ssim'] - q['ssim']:+.3f} SSIM; "
            f"sylva / peer: {s['step'] / q['step']:.2f}× wall time per step, "
            f"{s['rss'] / q['rss']:.2f}× peak memory"
        )


if __name__ == "__main__":
    main()
