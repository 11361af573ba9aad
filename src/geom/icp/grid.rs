//! Exact nearest-neighbour search within a radius for ICP correspondences: a grid of vertical
//! columns over the target's x, y extent, each column's points sorted by height, searched
//! ring by ring outwards from the query's column with the best distance so far as the bound.
//!
//! ICP asks the same question every iteration about points that barely moved, so each query
//! starts from the previous iteration's correspondence (its current distance is an upper
//! bound of the nearest distance): the ring walk then touches one or a few columns and a
//! short height window in each. Queries that find nothing within [`FALLBACK_RINGS`] rings
//! (far outliers) are answered by the k-d tree instead, so the worst case stays a tree query.
//! Results are exact: the nearest target point within the radius (ties by either).

use glam::Vec3;
use rayon::prelude::*;

/// Target points per column on average over the x, y bounding box: a few points per
/// column keep the ring walk short; tall columns (stems) are cut by the height window.
/// Chosen on the 82 k-point tile of `sylva bench geom`: 2 (5 cm columns there) took about
/// 25 % more CPU than 8 (10 cm columns).
const POINTS_PER_COLUMN: f32 = 8.0;

/// Rings walked before a query is handed to the k-d tree.
pub(super) const FALLBACK_RINGS: i64 = 3;

/// No point.
pub(super) const NONE: u32 = u32::MAX;

/// Neighbours kept per query by [`ColumnGrid::nearest_k`]: on a surface the clearance is
/// then about two point spacings, well beyond ICP's sub-millimetre late steps (see
/// `icp::Slot`). Chosen on `sylva bench geom --icp-tile-m 100`: 2, 4 and 8 took 0.39–0.47,
/// 0.51 and 0.72 CPU s (shared cores); 4 leaves room for SfM noise off the surface.
pub(super) const KNN: usize = 4;

/// Rings [`ColumnGrid::nearest_k`] walks before handing a query back.
pub(super) const KNN_RINGS: i64 = 4;

/// Up to [`KNN`] neighbours, nearest first: squared distance (m²), target index, position.
#[derive(Debug, Clone, Copy)]
pub(super) struct Knn {
    pub(super) n: usize,
    pub(super) d2: [f32; KNN],
    pub(super) index: [u32; KNN],
    pub(super) pos: [Vec3; KNN],
}

impl Default for Knn {
    fn default() -> Self {
        Self {
            n: 0,
            d2: [0.0; KNN],
            index: [NONE; KNN],
            pos: [Vec3::ZERO; KNN],
        }
    }
}

impl Knn {
    /// Squared distance a point must beat to enter: the last kept one's when full.
    fn bound(&self, max_d2: f32) -> f32 {
        if self.n == KNN {
            self.d2[KNN - 1]
        } else {
            max_d2
        }
    }

    /// Inserts a point at squared distance `d2` if it is within `max_d2` and beats the
    /// bound; true when it entered.
    fn offer(&mut self, d2: f32, index: u32, pos: Vec3, max_d2: f32) -> bool {
        if d2 > max_d2 || (self.n == KNN && d2 >= self.d2[KNN - 1]) {
            return false;
        }
        let mut k = self.n.min(KNN - 1);
        while k > 0 && self.d2[k - 1] > d2 {
            self.d2[k] = self.d2[k - 1];
            self.index[k] = self.index[k - 1];
            self.pos[k] = self.pos[k - 1];
            k -= 1;
        }
        self.d2[k] = d2;
        self.index[k] = index;
        self.pos[k] = pos;
        self.n = (self.n + 1).min(KNN);
        true
    }
}

/// One target point in column order: position and its index in the target slice.
#[derive(Debug, Clone, Copy, Default)]
struct Entry {
    x: f32,
    y: f32,
    z: f32,
    index: u32,
}

/// Columns over the target's x, y bounding box.
#[derive(Debug)]
pub(super) struct ColumnGrid {
    x0: f32,
    y0: f32,
    /// Column edge, metres.
    h: f32,
    inv_h: f32,
    nx: i64,
    ny: i64,
    /// Start of each column in `entries` (column cx + nx * cy), then the total.
    starts: Vec<u32>,
    entries: Vec<Entry>,
    /// Position in `entries` of each target point.
    slot: Vec<u32>,
}

impl ColumnGrid {
    /// Builds the grid over finite `points` (at most `u32::MAX - 1`; `None` when empty).
    pub(super) fn new(points: &[Vec3]) -> Option<Self> {
        let first = *points.first()?;
        if points.len() >= NONE as usize {
            return None;
        }
        let (lo, hi) = points
            .iter()
            .fold((first, first), |(lo, hi), p| (lo.min(*p), hi.max(*p)));
        let (w, d) = ((hi.x - lo.x).max(0.0), (hi.y - lo.y).max(0.0));
        let n = points.len() as f32;
        let mut h = ((w * d).max(w.max(d) * 1e-3) * POINTS_PER_COLUMN / n).sqrt();
        if !(h.is_finite() && h > 0.0) {
            h = 1.0; // all points on one vertical line
        }
        // At most about 4 columns per point (and never more than 2^26).
        let cap = (4.0 * n + 16.0).min((1u64 << 26) as f32);
        loop {
            let cells = ((w / h).floor() + 1.0) * ((d / h).floor() + 1.0);
            if cells <= cap {
                break;
            }
            h *= (cells / cap).sqrt().max(1.01);
        }
        let inv_h = 1.0 / h;
        let nx = (w * inv_h).floor() as i64 + 1;
        let ny = (d * inv_h).floor() as i64 + 1;
        let col = |p: &Vec3| {
            let cx = (((p.x - lo.x) * inv_h) as i64).clamp(0, nx - 1);
            let cy = (((p.y - lo.y) * inv_h) as i64).clamp(0, ny - 1);
            (cx + nx * cy) as usize
        };
        let ncol = (nx * ny) as usize;
        let cols: Vec<u32> = points.par_iter().map(|p| col(p) as u32).collect();
        let mut starts = vec![0u32; ncol + 1];
        for &c in &cols {
            starts[c as usize + 1] += 1;
        }
        for c in 0..ncol {
            starts[c + 1] += starts[c];
        }
        let mut fill = starts.clone();
        let mut entries = vec![Entry::default(); points.len()];
        for (i, (p, &c)) in points.iter().zip(&cols).enumerate() {
            let c = c as usize;
            entries[fill[c] as usize] = Entry {
                x: p.x,
                y: p.y,
                z: p.z,
                index: i as u32,
            };
            fill[c] += 1;
        }
        // Each column by height, columns in parallel.
        let mut columns: Vec<&mut [Entry]> = Vec::new();
        let mut rest = entries.as_mut_slice();
        for c in 0..ncol {
            let (column, tail) = rest.split_at_mut((starts[c + 1] - starts[c]) as usize);
            if column.len() > 1 {
                columns.push(column);
            }
            rest = tail;
        }
        columns
            .par_iter_mut()
            .with_min_len(256)
            .for_each(|c| c.sort_unstable_by(|a, b| a.z.total_cmp(&b.z)));
        let mut slot = vec![0u32; points.len()];
        for (k, e) in entries.iter().enumerate() {
            slot[e.index as usize] = k as u32;
        }
        Some(ColumnGrid {
            slot,
            x0: lo.x,
            y0: lo.y,
            h,
            inv_h,
            nx,
            ny,
            starts,
            entries,
        })
    }

    /// Walks the columns ring by ring outwards from `q`'s column, calling `visit(state, x, y)`
    /// for each column in the grid, until no column left can hold a point within
    /// `bound(state)` (squared metres) of `q` (true), or past `rings` rings or for a
    /// non-finite or far-off `q` (false: unsettled).
    fn walk_rings<S>(
        &self,
        q: Vec3,
        rings: i64,
        state: &mut S,
        bound: impl Fn(&S) -> f32,
        mut visit: impl FnMut(&mut S, i64, i64),
    ) -> bool {
        let fx = ((q.x - self.x0) * self.inv_h).floor();
        let fy = ((q.y - self.y0) * self.inv_h).floor();
        if !(fx.is_finite() && fy.is_finite()) || fx.abs() > 1e9 || fy.abs() > 1e9 {
            return false;
        }
        let (cx, cy) = (fx as i64, fy as i64);
        let mut k = 0i64;
        loop {
            if k >= 1 {
                // Points of ring k lie more than (k - 1) h away horizontally.
                let gap = (k - 1) as f32 * self.h * 0.999;
                if gap * gap > bound(state) {
                    return true;
                }
                // Rings 0..k cover the whole grid: nothing is left.
                if cx - (k - 1) <= 0
                    && cx + (k - 1) >= self.nx - 1
                    && cy - (k - 1) <= 0
                    && cy + (k - 1) >= self.ny - 1
                {
                    return true;
                }
            }
            if k > rings {
                return false;
            }
            let mut cell = |x: i64, y: i64| {
                if x >= 0 && x < self.nx && y >= 0 && y < self.ny {
                    visit(state, x, y);
                }
            };
            if k == 0 {
                cell(cx, cy);
            } else {
                for x in cx - k..=cx + k {
                    cell(x, cy - k);
                    cell(x, cy + k);
                }
                for y in cy - k + 1..cy + k {
                    cell(cx - k, y);
                    cell(cx + k, y);
                }
            }
            k += 1;
        }
    }

    /// Squared horizontal distance from `q` to column (x, y)'s box (shrunk by 0.1 % so
    /// rounding never prunes a column that holds a point within the bound).
    fn column_gap2(&self, x: i64, y: i64, q: Vec3) -> f32 {
        let bx0 = self.x0 + x as f32 * self.h;
        let by0 = self.y0 + y as f32 * self.h;
        let dx = (bx0 - q.x).max(q.x - (bx0 + self.h)).max(0.0) * 0.999;
        let dy = (by0 - q.y).max(q.y - (by0 + self.h)).max(0.0) * 0.999;
        dx * dx + dy * dy
    }

    /// The nearest point to `q` closer than `best.0` (squared metres; equal counts while
    /// `best.1` is [`NONE`]), as (squared distance, target index), or `best` when none is.
    /// `None` when the walk reached [`FALLBACK_RINGS`] rings without settling: ask the tree.
    pub(super) fn nearest(&self, q: Vec3, best: (f32, u32)) -> Option<(f32, u32)> {
        // The hint's place in its column: that column's scan starts there, no search.
        let hint = self
            .slot
            .get(best.1 as usize)
            .map_or(usize::MAX, |&k| k as usize);
        let mut best = best;
        let settled = self.walk_rings(
            q,
            FALLBACK_RINGS,
            &mut best,
            |b| b.0,
            |b, x, y| self.scan(x, y, q, hint, &mut b.0, &mut b.1),
        );
        settled.then_some(best)
    }

    /// The up to [`KNN`] nearest points to `q` within `sqrt(max_d2)`, nearest first, into
    /// `out`, and the clearance: the squared distance (m²) from `q` within which `out` holds
    /// every point (the last one's, or `max_d2` when fewer were found, where no other point
    /// lies within `max_d2`). `None` when the walk reached [`KNN_RINGS`] rings without
    /// settling (`out` is then incomplete): ask the tree.
    pub(super) fn nearest_k(&self, q: Vec3, max_d2: f32, out: &mut Knn) -> Option<f32> {
        out.n = 0;
        let settled = self.walk_rings(
            q,
            KNN_RINGS,
            out,
            |o| o.bound(max_d2),
            |o, x, y| self.scan_k(x, y, q, max_d2, o),
        );
        settled.then(|| out.bound(max_d2))
    }

    /// Adds the points of column (x, y) closer than `out`'s bound to `out`.
    fn scan_k(&self, x: i64, y: i64, q: Vec3, max_d2: f32, out: &mut Knn) {
        if self.column_gap2(x, y, q) > out.bound(max_d2) {
            return;
        }
        let c = (x + self.nx * y) as usize;
        let col = &self.entries[self.starts[c] as usize..self.starts[c + 1] as usize];
        let reach = |out: &Knn| out.bound(max_d2).sqrt() * 1.0001 + 1e-7;
        let mid = col.partition_point(|e| e.z < q.z);
        let (mut down, mut up) = (mid, mid);
        let mut r = reach(out);
        loop {
            let dn = (down > 0 && col[down - 1].z >= q.z - r).then(|| q.z - col[down - 1].z);
            let un = (up < col.len() && col[up].z <= q.z + r).then(|| col[up].z - q.z);
            let e = match (dn, un) {
                (None, None) => break,
                (Some(d), Some(u)) if d <= u => {
                    down -= 1;
                    &col[down]
                }
                (Some(_), None) => {
                    down -= 1;
                    &col[down]
                }
                _ => {
                    up += 1;
                    &col[up - 1]
                }
            };
            let p = Vec3::new(e.x, e.y, e.z);
            let d = p - q;
            if out.offer(d.x * d.x + d.y * d.y + d.z * d.z, e.index, p, max_d2) {
                r = reach(out);
            }
        }
    }

    /// Scans column (x, y) for points closer than the best so far; `hint` is the position
    /// in `entries` of a point within the best distance (or `usize::MAX`).
    fn scan(&self, x: i64, y: i64, q: Vec3, hint: usize, bd2: &mut f32, bi: &mut u32) {
        if self.column_gap2(x, y, q) > *bd2 {
            return;
        }
        let c = (x + self.nx * y) as usize;
        let (a, b) = (self.starts[c] as usize, self.starts[c + 1] as usize);
        let col = &self.entries[a..b];
        let mut reach = bd2.sqrt() * 1.0001 + 1e-7;
        let mut visit = |e: &Entry, reach: &mut f32| {
            let (ex, ey, ez) = (e.x - q.x, e.y - q.y, e.z - q.z);
            let d2 = ex * ex + ey * ey + ez * ez;
            if d2 < *bd2 || (d2 == *bd2 && *bi == NONE) {
                *bd2 = d2;
                *bi = e.index;
                *reach = d2.sqrt() * 1.0001 + 1e-7;
            }
        };
        // Walk down and up from the hint (within the window) or from q's height, nearer
        // height first so the bound shrinks early; each side stops at the window's edge.
        let mid = if (a..b).contains(&hint) {
            hint - a
        } else {
            col.partition_point(|e| e.z < q.z)
        };
        let (mut down, mut up) = (mid, mid); // next: col[down - 1] and col[up]
        loop {
            let dn = (down > 0 && col[down - 1].z >= q.z - reach).then(|| q.z - col[down - 1].z);
            let un = (up < col.len() && col[up].z <= q.z + reach).then(|| col[up].z - q.z);
            match (dn, un) {
                (None, None) => break,
                (Some(d), Some(u)) if d.abs() <= u.abs() => {
                    down -= 1;
                    visit(&col[down], &mut reach);
                }
                (Some(_), None) => {
                    down -= 1;
                    visit(&col[down], &mut reach);
                }
                _ => {
                    visit(&col[up], &mut reach);
                    up += 1;
                }
            }
        }
    }
}

#[cfg(test)]
pub(super) mod tests {
    use super::*;
    use rand::{RngExt, SeedableRng, rngs::ChaCha8Rng};

    /// The smallest squared distance from `q` to `points` within `max_d2`, by brute force.
    pub(in crate::geom::icp) fn brute(points: &[Vec3], q: Vec3, max_d2: f32) -> Option<f32> {
        points
            .iter()
            .map(|p| {
                let e = *p - q;
                e.x * e.x + e.y * e.y + e.z * e.z
            })
            .filter(|d2| *d2 <= max_d2)
            .min_by(f32::total_cmp)
    }

    /// k nearest within a radius against brute force: the same distances, nearest first,
    /// and no point left out inside the clearance.
    #[test]
    fn nearest_k_matches_brute_force_and_its_clearance_holds() {
        let mut rng = ChaCha8Rng::seed_from_u64(8);
        let mut pts: Vec<Vec3> = (0..4000)
            .map(|_| {
                let (x, y) = (rng.random::<f32>() * 4.0, rng.random::<f32>() * 4.0);
                Vec3::new(x, y, 0.1 * (x * 2.0).sin())
            })
            .collect();
        for i in 0..600 {
            let a = i as f32 * 0.9;
            pts.push(Vec3::new(
                2.0 + 0.1 * a.cos(),
                2.0 + 0.1 * a.sin(),
                i as f32 * 0.01,
            ));
        }
        pts.extend_from_within(0..50);
        let grid = ColumnGrid::new(&pts).unwrap();
        let mut out = Knn::default();
        for qi in 0..1500 {
            let q = if qi % 2 == 0 {
                pts[rng.random_range(0..pts.len())] + Vec3::splat(0.004)
            } else {
                Vec3::new(
                    rng.random::<f32>() * 5.0 - 0.5,
                    rng.random::<f32>() * 5.0 - 0.5,
                    rng.random::<f32>() * 7.0 - 0.5,
                )
            };
            for max_d in [0.02f32, 0.1, 0.3] {
                let max_d2 = max_d * max_d;
                let Some(clear2) = grid.nearest_k(q, max_d2, &mut out) else {
                    continue;
                };
                let mut all: Vec<(f32, u32)> = pts
                    .iter()
                    .enumerate()
                    .map(|(i, p)| ((*p - q).length_squared(), i as u32))
                    .filter(|(d2, _)| *d2 <= max_d2)
                    .collect();
                all.sort_by(|a, b| a.0.total_cmp(&b.0));
                assert_eq!(out.n, all.len().min(KNN), "query {q} within {max_d}");
                for k in 0..out.n {
                    assert!((out.d2[k] - all[k].0).abs() <= 1e-9);
                    assert_eq!(out.pos[k], pts[out.index[k] as usize]);
                }
                if out.n < KNN {
                    assert_eq!(clear2, max_d2);
                }
                for (i, p) in pts.iter().enumerate() {
                    if !out.index[..out.n].contains(&(i as u32)) {
                        assert!((*p - q).length_squared() >= clear2 * 0.9999);
                    }
                }
            }
        }
    }

    /// Random stems and ground with duplicates; queries near and far, with and without a
    /// hint, against brute force.
    #[test]
    fn nearest_within_radius_matches_brute_force() {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let mut pts: Vec<Vec3> = (0..3000)
            .map(|_| Vec3::new(rng.random::<f32>() * 4.0, rng.random::<f32>() * 4.0, 0.0))
            .collect();
        for s in 0..5 {
            let (sx, sy) = (rng.random::<f32>() * 4.0, rng.random::<f32>() * 4.0);
            for i in 0..400 {
                let a = i as f32 * 0.7;
                pts.push(Vec3::new(
                    sx + 0.1 * a.cos(),
                    sy + 0.1 * a.sin(),
                    i as f32 * 0.02 + s as f32,
                ));
            }
        }
        for i in 0..100 {
            pts.push(pts[i * 13]);
        }
        let grid = ColumnGrid::new(&pts).unwrap();
        for qi in 0..2000 {
            let q = if qi % 3 == 0 {
                pts[rng.random_range(0..pts.len())] + Vec3::splat(0.003)
            } else {
                Vec3::new(
                    rng.random::<f32>() * 6.0 - 1.0,
                    rng.random::<f32>() * 6.0 - 1.0,
                    rng.random::<f32>() * 10.0 - 1.0,
                )
            };
            for max_d in [0.01f32, 0.2, 1.0, 30.0] {
                let max_d2 = max_d * max_d;
                let want = brute(&pts, q, max_d2);
                // With a random (valid) hint and without one.
                let hint = rng.random_range(0..pts.len());
                let e = pts[hint] - q;
                let hd2 = e.x * e.x + e.y * e.y + e.z * e.z;
                for start in [(max_d2, NONE), (hd2.min(max_d2), hint as u32)] {
                    if start.1 != NONE && hd2 > max_d2 {
                        continue;
                    }
                    let got = grid.nearest(q, start).map(|(d2, i)| {
                        if i == NONE {
                            return None;
                        }
                        let e = pts[i as usize] - q;
                        assert_eq!(d2, e.x * e.x + e.y * e.y + e.z * e.z);
                        Some(d2)
                    });
                    // A query 3 mm from a point is settled by the grid, never handed back.
                    assert!(qi % 3 != 0 || got.is_some(), "near query {q} handed back");
                    if let Some(got) = got {
                        match (got, want) {
                            (None, None) => {}
                            (Some(g), Some(w)) => assert!((g - w).abs() <= 1e-9, "{g} vs {w}"),
                            _ => panic!("query {q} within {max_d}: got {got:?}, want {want:?}"),
                        }
                    }
                }
            }
        }
    }
}
