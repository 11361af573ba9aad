"""Helpers of benches/open3d_compare.sh (run with the venv's python; see that script).

  open3d_compare.py tile SRC.laz OUT.laz NT      the make_plot10m.py recipe with NT x NT copies,
                                                  written copy by copy (bounded memory)
  open3d_compare.py prefix IN.laz OUT.laz N       the first N points of IN, file order kept
  open3d_compare.py o3d IN.laz OUT.json [EDGE]    laspy read + Open3D phases, rows as JSON;
                                                  EDGE: the ICP tile's edge, m (default 10)
  open3d_compare.py table O3D.json SYLVA.json     prints operation, Open3D s, sylva s, ratio

The tiling recipe is the one in the docstring of ../shared/bench/make_plot10m.py (TreeLS
pine_plot.laz copied NT x NT times, 10.5 m apart, with a splitmix64 jitter of +-2 mm, LAS 1.2
point format 0, scale 1e-4, offset 0); `tile` re-implements it from that text so that clouds
larger than 9 x 9 copies can be built without holding them in memory (copy c = NT*i + j,
global index g = c*N + p, as in the recipe).
"""
import json
import math
import resource
import sys
import time

import laspy
import numpy as np

STEP = 10.5
JIT = 0.004
ICP_TILE_M = 10.0  # default; sylva bench geom --icp-tile-m


def splitmix64(s):
    s = s.astype(np.uint64)
    with np.errstate(over="ignore"):
        z = s + np.uint64(0x9E3779B97F4A7C15)
        z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        z = z ^ (z >> np.uint64(31))
    return z


def header():
    hdr = laspy.LasHeader(point_format=0, version="1.2")
    hdr.scales = np.array([1e-4, 1e-4, 1e-4])
    hdr.offsets = np.array([0.0, 0.0, 0.0])
    return hdr


def tile(src_path, out_path, nt):
    t0 = time.time()
    las = laspy.read(src_path)
    src = np.c_[las.x, las.y, las.z].astype(np.float64)
    n = len(src)
    pidx = np.arange(n, dtype=np.uint64)
    with laspy.open(out_path, mode="w", header=header(),
                    laz_backend=laspy.LazBackend.LazrsParallel) as w:
        for i in range(nt):
            for j in range(nt):
                c = nt * i + j
                g = np.uint64(c * n) + pidx
                blk = src.copy()
                blk[:, 0] += STEP * i
                blk[:, 1] += STEP * j
                for a in range(3):
                    h = splitmix64(np.uint64(3) * g + np.uint64(a))
                    u = (h >> np.uint64(11)).astype(np.float64) * (2.0 ** -53)
                    blk[:, a] += (u - 0.5) * JIT
                rec = laspy.ScaleAwarePointRecord.zeros(n, header=w.header)
                rec.x = blk[:, 0]
                rec.y = blk[:, 1]
                rec.z = blk[:, 2]
                w.write_points(rec)
    print(f"wrote {out_path}: {n * nt * nt} points ({nt}x{nt} copies) in {time.time() - t0:.1f} s")


def prefix(in_path, out_path, n):
    las = laspy.read(in_path)
    out = laspy.LasData(header())
    out.x = np.asarray(las.x[:n])
    out.y = np.asarray(las.y[:n])
    out.z = np.asarray(las.z[:n])
    out.write(out_path, laz_backend=laspy.LazBackend.LazrsParallel)
    print(f"wrote {out_path}: first {len(out.x)} points of {in_path}")


def peak_mib():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def icp_truth(c):
    """The motion of sylva's `icp_truth`: 0.5 deg about the vertical through c, then (5,-3,2) cm."""
    a = math.radians(0.5)
    r = np.array([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0, 0, 1.0]])
    t = c - r @ c + np.array([0.05, -0.03, 0.02])
    m = np.eye(4)
    m[:3, :3] = r
    m[:3, 3] = t
    return m


def icp_point_to_plane(o3d, source, target):
    """The benchmark's registration: 0.2 m, identity start, Open3D's default criteria."""
    return o3d.pipelines.registration.registration_icp(
        source, target, 0.2, np.eye(4),
        o3d.pipelines.registration.TransformationEstimationPointToPlane(),
        o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=50))


def icp_iterations(o3d, source, target):
    """Iterations Open3D's ICP ran (its RegistrationResult does not say): the same run again,
    not timed, with the Debug log (one "ICP Iteration #k" line per iteration) sent to a file
    (the log is written by C++ to file descriptor 1)."""
    import os
    import tempfile

    with tempfile.TemporaryFile(mode="w+") as log:
        sys.stdout.flush()
        saved = os.dup(1)
        os.dup2(log.fileno(), 1)
        try:
            o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Debug)
            icp_point_to_plane(o3d, source, target)
        finally:
            o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Warning)
            sys.stdout.flush()
            os.dup2(saved, 1)
            os.close(saved)
        log.seek(0)
        return sum(1 for line in log if "ICP Iteration #" in line)


def run_o3d(in_path, json_path, edge=ICP_TILE_M):
    import open3d as o3d

    print(f"open3d {o3d.__version__}, laspy {laspy.__version__} (lazrs parallel)")
    rows = []

    class Clock:
        def __init__(self):
            self.wall, self.cpu = time.perf_counter(), time.process_time()

        def read(self):
            return time.perf_counter() - self.wall, time.process_time() - self.cpu

    def row(phase, n_in, n_out, clock, note=""):
        secs, cpu = clock
        r = dict(phase=phase, points_in=n_in, points_out=n_out, seconds=secs, cpu_seconds=cpu,
                 peak_rss_mib=peak_mib(), note=note)
        print(f"| {phase:<28} | {n_in:>10} | {n_out:>10} | {secs:>8.3f} | {cpu:>8.3f} "
              f"| {r['peak_rss_mib']:>9.0f} | {note}")
        rows.append(r)

    print(f"| {'phase':<28} | {'points in':>10} | {'points out':>10} | {'seconds':>8} | {'CPU s':>8} "
          f"| {'peak MiB':>9} | note")

    t = Clock()
    las = laspy.read(in_path, laz_backend=laspy.LazBackend.LazrsParallel)
    secs = t.read()
    xyz = np.ascontiguousarray(np.c_[las.x, las.y, las.z], dtype=np.float64)
    del las
    row("read", len(xyz), len(xyz), secs, "laspy.read, lazrs parallel")

    # ICP tile: x, y in [floor(min), floor(min) + edge) m, coordinates relative to that corner.
    corner = np.array([math.floor(xyz[:, 0].min()), math.floor(xyz[:, 1].min()), 0.0])
    sel = ((xyz[:, 0] >= corner[0]) & (xyz[:, 0] < corner[0] + edge)
           & (xyz[:, 1] >= corner[1]) & (xyz[:, 1] < corner[1] + edge))
    tile_pts = xyz[sel] - corner

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz))
    del xyz
    t = Clock()
    vox = pcd.voxel_down_sample(0.02)
    row("voxel_down_sample(0.02)", len(pcd.points), len(vox.points), t.read())
    del pcd

    t = Clock()
    _, ind = vox.remove_statistical_outlier(16, 2.5)
    kept = vox.select_by_index(ind)
    row("statistical_outlier(16, 2.5)", len(vox.points), len(kept.points), t.read())
    del vox

    t = Clock()
    kept.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(20))
    row("estimate_normals(knn 20)", len(kept.points), len(kept.normals), t.read())
    del kept

    target = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(tile_pts))
    target.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(20))  # input, not timed
    truth = icp_truth(np.array([edge / 2, edge / 2, 0.0]))
    inv = np.linalg.inv(truth)
    src = tile_pts[::4] @ inv[:3, :3].T + inv[:3, 3]
    source = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(src))
    t = Clock()
    res = icp_point_to_plane(o3d, source, target)
    secs = t.read()
    its = icp_iterations(o3d, source, target)
    m = np.asarray(res.transformation)
    rot_err = math.degrees(np.abs(m[:3, :3] @ truth[:3, :3].T - np.eye(3)).max())
    t_err = np.linalg.norm(m[:3, 3] - truth[:3, 3]) * 1000
    row("icp point-to-plane, tile", len(tile_pts), len(src), secs,
        f"{its} its, fitness {res.fitness:.3f}, rmse {res.inlier_rmse:.4f} m, "
        f"rot err {rot_err:.4f} deg, t err {t_err:.2f} mm")
    with open(json_path, "w") as f:
        json.dump(dict(open3d=o3d.__version__, rows=rows), f, indent=1)


# (Open3D phase prefix, sylva phase prefix, row name)
KEYS = [("read", "read", "read the LAZ"), ("voxel", "voxel", "voxel_down_sample(0.02)"),
        ("statistical", "statistical", "statistical outlier (16, 2.5)"),
        ("estimate", "estimate", "normals (KNN 20)"),
        ("icp", "icp point-to-plane", "ICP point-to-plane (target points in)"),
        ("icp", "icp every point", "ICP, sylva on every point every iteration")]


def table(o3d_json, sylva_json):
    o = json.load(open(o3d_json))
    s = json.load(open(sylva_json))
    orows, srows = o["rows"], s

    def find(rows, key):
        return next((r for r in rows if r["phase"].startswith(key)), None)

    print(f"| operation | points in | Open3D {o['open3d']} s (laspy+lazrs for read) | sylva s "
          "| ratio | Open3D CPU s | sylva CPU s | CPU ratio |")
    print("|---|---|---|---|---|---|---|---|")
    for okey, skey, name in KEYS:
        a, b = find(orows, okey), find(srows, skey)
        if a is None or b is None:
            continue
        ratio = a["seconds"] / max(b["seconds"], 1e-9)
        cratio = a["cpu_seconds"] / max(b["cpu_seconds"], 1e-9)
        print(f"| {name} | {b['points_in']:,} | {a['seconds']:.3f} | {b['seconds']:.3f} | {ratio:.1f}x "
              f"| {a['cpu_seconds']:.3f} | {b['cpu_seconds']:.3f} | {cratio:.1f}x |")
    po = max(r["peak_rss_mib"] for r in orows)
    ps = max(r["peak_rss_mib"] for r in srows)
    print(f"| peak RSS (MiB) | | {po:.0f} | {ps:.0f} | |")


def main():
    cmd = sys.argv[1] if len(sys.argv) > 1 else ""
    if cmd == "tile":
        tile(sys.argv[2], sys.argv[3], int(sys.argv[4]))
    elif cmd == "prefix":
        prefix(sys.argv[2], sys.argv[3], int(sys.argv[4]))
    elif cmd == "o3d":
        run_o3d(sys.argv[2], sys.argv[3], float(sys.argv[4]) if len(sys.argv) > 4 else ICP_TILE_M)
    elif cmd == "table":
        table(sys.argv[2], sys.argv[3])
    else:
        sys.exit(__doc__)


if __name__ == "__main__":
    main()
