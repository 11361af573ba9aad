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
CPU_S = re.compile(r"(?:User|System) time \(seconds\): ([0-9.]+)")


def timed(cmd, env=None):
    """Runs cmd under GNU time -v; returns (wall s, peak RSS MiB, combined output). The
    output ends with GNU time's report, whose user + system CPU seconds [`cpu_seconds`] read
    the same whether or not other work shares the machine."""
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


def cpu_seconds(text):
    """User + system CPU seconds from GNU time's report."""
    return sum(float(v) for v in CPU_S.findall(text)[-2:])


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
        "sylva_psnr": float(m.group(1)),
        "sylva_ssim": float(m.group(2)),
        "views": int(m.group(3)),
        "gaussians": int(m.group(4)),
        "loop_s_per_step": 1.0 / float(m.group(5)),
        "cpu": cpu_seconds(text),
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
    ply = newest_ply(out)
    ours = sylva_eval(a, ply, os.path.join(work, f"peer-{rnd}-sylva-eval")) if ply else None
    return {
        "trainer": "peer",
        "psnr": float(psnr),
        "ssim": float(ssim),
        "sylva_psnr": ours[0] if ours else None,
        "sylva_ssim": ours[1] if ours else None,
        "views": None,
        "gaussians": ply_vertices(out),
        "loop_s_per_step": peer_loop_s_per_step(text),
        "cpu": cpu_seconds(text),
        "wall": wall,
        "rss": rss,
    }


def newest_ply(folder):
    files = sorted(glob.glob(os.path.join(folder, "**", "*.ply"), recursive=True), key=os.path.getmtime)
    return files[-1] if files else None


def sylva_eval(a, ply, out):
    """The peer's exported splats measured by Sylva's evaluator: `sylva train --steps 0 --init
    PLY`, the same held-out photos at the same pixels, no cap on the Gaussians; (PSNR, SSIM)."""
    cmd = [
        a.sylva, "train", "--colmap", a.colmap, "--out", out, "--steps", "0",
        "--resolution", str(a.resolution), "--init", ply, "--exposure", "off",
        "--max-gaussians", str(2**31 - 1),
    ]
    _, _, text = timed(cmd)
    m = SYLVA_LINE.search(text)
    return (float(m.group(1)), float(m.group(2))) if m else None


# env_logger's timestamped lines, e.g. "[2026-11-27T17:01:02Z INFO  brush_process...] ...".
LOG_TIME = re.compile(r"^\[(\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d(?:\.\d+)?)Z? ", re.M)
PEER_ITER = re.compile(r"^\[(\S+?)Z? .*?(?:[Ii]ter(?:ation)?|step)[ =:]+(\d+)", re.M)


def peer_loop_s_per_step(text):
    """The peer's training-loop seconds per step from its log: between the first and last
    timestamped lines that name an iteration (None where the log has no such lines)."""
    import datetime

    hits = []
    for stamp, it in PEER_ITER.findall(text):
        try:
            t = datetime.datetime.fromisoformat(stamp)
        except ValueError:
            continue
        hits.append((int(it), t))
    if len(hits) < 2:
        return None
    (i0, t0), (i1, t1) = min(hits), max(hits)
    return (t1 - t0).total_seconds() / (i1 - i0) if i1 > i0 else None


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
    print("PSNR and SSIM: each trainer's own evaluator; Sylva-eval: the same exported splats measured by Sylva's")
    print("| round | trainer | PSNR dB | SSIM | Sylva-eval PSNR dB | Sylva-eval SSIM | Gaussians | wall s | wall s/step | loop s/step | CPU s | peak MiB |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    rows = []
    for rnd in range(1, a.rounds + 1):
        runs = [run_sylva(a, a.work, rnd)]
        if a.peer:
            runs.append(run_peer(a, a.work, rnd))
        for r in runs:
            rows.append(r)
            print(
                f"| {rnd} | {r['trainer']} | {r['psnr']:.2f} | {r['ssim']:.3f} | "
                f"{fmt(r['sylva_psnr'], '.2f')} | {fmt(r['sylva_ssim'], '.3f')} | "
                f"{fmt(r['gaussians'], 'd')} | {r['wall']:.1f} | {r['wall'] / a.steps:.3f} | "
                f"{fmt(r['loop_s_per_step'], '.3f')} | {r['cpu']:.0f} | {r['rss']:.0f} |",
                flush=True,
            )
    print("\n| trainer | PSNR dB (own) | SSIM (own) | PSNR dB (Sylva-eval) | SSIM (Sylva-eval) | Gaussians | wall s/step | loop s/step | CPU s | peak MiB |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    means = {}

    def avg(rs, key):
        v = [r[key] for r in rs if r[key] is not None]
        return statistics.mean(v) if v else None

    for t in ["sylva", "peer"]:
        rs = [r for r in rows if r["trainer"] == t]
        if not rs:
            continue
        for r in rs:
            r["step"] = r["wall"] / a.steps
        means[t] = {k: avg(rs, k) for k in
                    ["psnr", "ssim", "sylva_psnr", "sylva_ssim", "gaussians", "step", "loop_s_per_step", "cpu", "rss"]}
        m = means[t]
        print(
            f"| {t} | {m['psnr']:.2f} | {m['ssim']:.3f} | {fmt(m['sylva_psnr'], '.2f')} | "
            f"{fmt(m['sylva_ssim'], '.3f')} | {fmt(m['gaussians'], '.0f')} | {m['step']:.3f} | "
            f"{fmt(m['loop_s_per_step'], '.3f')} | {m['cpu']:.0f} | {m['rss']:.0f} |"
        )
    if "peer" in means:
        s, q = means["sylva"], means["peer"]
        same = (
            f"{s['sylva_psnr'] - q['sylva_psnr']:+.2f} dB PSNR, {s['sylva_ssim'] - q['sylva_ssim']:+.3f} SSIM by Sylva's evaluator for both"
            if q["sylva_psnr"] is not None else "the peer's splats could not be measured by Sylva's evaluator"
        )
        loop = (
            f", {s['loop_s_per_step'] / q['loop_s_per_step']:.2f}× training-loop time per step"
            if q["loop_s_per_step"] else ""
        )
        print(
            f"\nsylva − peer: {same} ({s['psnr'] - q['psnr']:+.2f} dB, each by its own); "
            f"sylva / peer: {s['step'] / q['step']:.2f}× wall time per step{loop}, "
            f"{s['cpu'] / q['cpu']:.2f}× CPU seconds, "
            f"{s['rss'] / q['rss']:.2f}× peak memory"
        )

if __name__ == "__main__":
    main()
