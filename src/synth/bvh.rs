//! A bounding volume hierarchy over the scene's primitives: binned SAH build, flattened nodes,
//! stack-based traversal without allocation.
//!
//! The build bins primitive centroids into [`BINS`] buckets on each axis and takes the split
//! with the lowest surface-area-heuristic cost (Wald 2007, "On fast construction of SAH-based
//! bounding volume hierarchies"). Nodes are 32 bytes; the two children of an interior node
//! are stored next to each other. The caller reorders its primitives by [`Bvh::order`] so
//! that every leaf covers a contiguous range.

use glam::Vec3;

use super::shapes::Interval;

/// Centroid bins per axis (Wald 2007 uses 8–32).
const BINS: usize = 16;
/// Leaves hold at most this many primitives.
const MAX_LEAF: usize = 4;
/// Cost of one primitive test relative to one node visit.
const PRIM_COST: f32 = 1.5;
/// Traversal stack depth; the build keeps the tree shallower than this.
const STACK: usize = 64;

/// One flattened node: bounds, then either the first child (`count == 0`) or the first
/// primitive and the number of primitives (a leaf).
#[derive(Debug, Clone, Copy)]
#[repr(C)]
struct Node {
    min: [f32; 3],
    first: u32,
    max: [f32; 3],
    count: u32,
}

/// The hierarchy; primitive indices refer to the caller's array after reordering.
#[derive(Debug, Default)]
pub struct Bvh {
    nodes: Vec<Node>,
    /// New position `i` holds the primitive that was at `order[i]` before the build.
    pub order: Vec<u32>,
}

#[derive(Clone, Copy)]
struct Aabb {
    min: Vec3,
    max: Vec3,
}

impl Aabb {
    const EMPTY: Aabb = Aabb {
        min: Vec3::splat(f32::INFINITY),
        max: Vec3::splat(f32::NEG_INFINITY),
    };
    fn grow(&mut self, o: &Aabb) {
        self.min = self.min.min(o.min);
        self.max = self.max.max(o.max);
    }
    fn grow_point(&mut self, p: Vec3) {
        self.min = self.min.min(p);
        self.max = self.max.max(p);
    }
    fn area(&self) -> f32 {
        let e = (self.max - self.min).max(Vec3::ZERO);
        e.x * e.y + e.y * e.z + e.z * e.x
    }
}

impl Bvh {
    /// Builds the hierarchy over boxes (min, max). Deterministic for a given input.
    pub fn build(bounds: &[(Vec3, Vec3)]) -> Bvh {
        let boxes: Vec<Aabb> = bounds.iter().map(|&(min, max)| Aabb { min, max }).collect();
        let centroids: Vec<Vec3> = boxes.iter().map(|b| (b.min + b.max) * 0.5).collect();
        let mut order: Vec<u32> = (0..bounds.len() as u32).collect();
        let mut nodes = Vec::with_capacity(2 * bounds.len().max(1));
        nodes.push(Node {
            min: [0.0; 3],
            first: 0,
            max: [0.0; 3],
            count: 0,
        });
        // (node index, start, end, depth)
        let mut work = vec![(0usize, 0usize, bounds.len(), 0usize)];
        while let Some((ni, start, end, depth)) = work.pop() {
            let mut bb = Aabb::EMPTY;
            let mut cb = Aabb::EMPTY;
            for &i in &order[start..end] {
                bb.grow(&boxes[i as usize]);
                cb.grow_point(centroids[i as usize]);
            }
            nodes[ni].min = bb.min.to_array();
            nodes[ni].max = bb.max.to_array();
            let n = end - start;
            let split = if n <= 1 || depth >= STACK - 4 {
                None
            } else {
                best_split(&boxes, &centroids, &order[start..end], &cb, bb.area())
                    .or_else(|| (n > MAX_LEAF).then(|| median_split(&cb)))
            };
            let Some((axis, pos)) = split else {
                nodes[ni].first = start as u32;
                nodes[ni].count = n as u32;
                continue;
            };
            let slice = &mut order[start..end];
            let mut mid = partition(slice, |i| centroids[i as usize][axis] < pos);
            if mid == 0 || mid == n {
                // All centroids fell on one side (coincident centroids): split by count.
                slice.sort_by(|&a, &b| {
                    centroids[a as usize][axis]
                        .total_cmp(&centroids[b as usize][axis])
                        .then(a.cmp(&b))
                });
                mid = n / 2;
            }
            let left = nodes.len();
            nodes.push(Node {
                min: [0.0; 3],
                first: 0,
                max: [0.0; 3],
                count: 0,
            });
            nodes.push(Node {
                min: [0.0; 3],
                first: 0,
                max: [0.0; 3],
                count: 0,
            });
            nodes[ni].first = left as u32;
            nodes[ni].count = 0;
            work.push((left + 1, start + mid, end, depth + 1));
            work.push((left, start, start + mid, depth + 1));
        }
        Bvh { nodes, order }
    }

    /// At inner node `node`: the child the ray meets to visit next, the nearer one when it
    /// meets both (the farther is pushed on `stack`); `None` when it meets neither.
    #[inline(always)]
    fn descend(
        &self,
        node: &Node,
        o: Vec3,
        inv: Vec3,
        span: Interval,
        stack: &mut [u32; STACK],
        sp: &mut usize,
    ) -> Option<usize> {
        let (l, r) = (node.first as usize, node.first as usize + 1);
        match (
            slab(&self.nodes[l], o, inv, span),
            slab(&self.nodes[r], o, inv, span),
        ) {
            (Some(a), Some(b)) => {
                let (near, far) = if a <= b { (l, r) } else { (r, l) };
                stack[*sp] = far as u32;
                *sp += 1;
                Some(near)
            }
            (Some(_), None) => Some(l),
            (None, Some(_)) => Some(r),
            (None, None) => None,
        }
    }

    /// Nearest hit: (distance, primitive index) of the closest `hit(prim, span)` in `span`.
    #[inline]
    pub fn intersect(
        &self,
        o: Vec3,
        d: Vec3,
        mut span: Interval,
        mut hit: impl FnMut(u32, Interval) -> Option<f32>,
    ) -> Option<(f32, u32)> {
        let inv = d.recip();
        let mut best = None;
        let mut stack = [0u32; STACK];
        let mut sp = 0usize;
        let mut ni = 0usize;
        if self.nodes.is_empty() || slab(&self.nodes[0], o, inv, span).is_none() {
            return None;
        }
        loop {
            let node = &self.nodes[ni];
            if node.count > 0 {
                for p in node.first..node.first + node.count {
                    if let Some(t) = hit(p, span) {
                        span.max = t;
                        best = Some((t, p));
                    }
                }
            } else if let Some(next) = self.descend(node, o, inv, span, &mut stack, &mut sp) {
                ni = next;
                continue;
            }
            // Pop the next node that can still hold a closer hit.
            loop {
                if sp == 0 {
                    return best;
                }
                sp -= 1;
                let cand = stack[sp] as usize;
                if slab(&self.nodes[cand], o, inv, span).is_some() {
                    ni = cand;
                    break;
                }
            }
        }
    }

    /// True when any `hit(prim, span)` succeeds (shadow and visibility rays). Children are
    /// visited nearest first: occluders usually lie close to the ray's origin.
    #[inline]
    pub fn any(
        &self,
        o: Vec3,
        d: Vec3,
        span: Interval,
        mut hit: impl FnMut(u32, Interval) -> bool,
    ) -> bool {
        let inv = d.recip();
        let mut stack = [0u32; STACK];
        let mut sp = 0usize;
        if self.nodes.is_empty() || slab(&self.nodes[0], o, inv, span).is_none() {
            return false;
        }
        let mut ni = 0usize;
        loop {
            let node = &self.nodes[ni];
            if node.count > 0 {
                if (node.first..node.first + node.count).any(|p| hit(p, span)) {
                    return true;
                }
            } else if let Some(next) = self.descend(node, o, inv, span, &mut stack, &mut sp) {
                ni = next;
                continue;
            }
            if sp == 0 {
                return false;
            }
            sp -= 1;
            ni = stack[sp] as usize;
        }
    }
}

/// Entry distance of the ray into the node's box within `span`, if it enters at all.
#[inline]
fn slab(n: &Node, o: Vec3, inv: Vec3, span: Interval) -> Option<f32> {
    let t0 = (Vec3::from_array(n.min) - o) * inv;
    let t1 = (Vec3::from_array(n.max) - o) * inv;
    let lo = t0.min(t1);
    let hi = t0.max(t1);
    // NaN (0 * inf on a box face) compares false and is ignored by max/min element-wise.
    let tmin = lo.max_element().max(span.min);
    let tmax = hi.min_element().min(span.max);
    (tmin <= tmax).then_some(tmin)
}

/// Splits `slice` so that items with `left(item)` come first; returns their count.
fn partition(slice: &mut [u32], left: impl Fn(u32) -> bool) -> usize {
    let mut mid = 0;
    for i in 0..slice.len() {
        if left(slice[i]) {
            slice.swap(i, mid);
            mid += 1;
        }
    }
    mid
}

fn median_split(cb: &Aabb) -> (usize, f32) {
    let e = cb.max - cb.min;
    let axis = if e.x >= e.y && e.x >= e.z {
        0
    } else if e.y >= e.z {
        1
    } else {
        2
    };
    (axis, (cb.min[axis] + cb.max[axis]) * 0.5)
}

/// The binned-SAH split (axis, position) cheaper than making a leaf, if any; with more than
/// [`MAX_LEAF`] items the cheapest split is returned regardless.
#[allow(clippy::needless_range_loop)] // `axis` indexes both vectors and bounds.
fn best_split(
    boxes: &[Aabb],
    centroids: &[Vec3],
    items: &[u32],
    cb: &Aabb,
    parent_area: f32,
) -> Option<(usize, f32)> {
    let parent_area = parent_area.max(1e-12);
    let mut best: Option<(f32, usize, f32)> = None;
    for axis in 0..3 {
        let (lo, hi) = (cb.min[axis], cb.max[axis]);
        if hi - lo <= 1e-9 {
            continue;
        }
        let scale = BINS as f32 / (hi - lo);
        let mut bin_box = [Aabb::EMPTY; BINS];
        let mut bin_n = [0usize; BINS];
        for &i in items {
            let b = (((centroids[i as usize][axis] - lo) * scale) as usize).min(BINS - 1);
            bin_box[b].grow(&boxes[i as usize]);
            bin_n[b] += 1;
        }
        // Sweep from the right to get the area and count of every right part.
        let mut right_area = [0.0f32; BINS];
        let mut right_n = [0usize; BINS];
        let mut acc = Aabb::EMPTY;
        let mut cnt = 0;
        for b in (1..BINS).rev() {
            acc.grow(&bin_box[b]);
            cnt += bin_n[b];
            right_area[b] = acc.area();
            right_n[b] = cnt;
        }
        let mut acc = Aabb::EMPTY;
        let mut cnt = 0;
        for b in 0..BINS - 1 {
            acc.grow(&bin_box[b]);
            cnt += bin_n[b];
            if cnt == 0 || right_n[b + 1] == 0 {
                continue;
            }
            let sum = acc.area() * cnt as f32 + right_area[b + 1] * right_n[b + 1] as f32;
            let cost = 1.0 + PRIM_COST * sum / parent_area;
            let pos = lo + (b + 1) as f32 / scale;
            if best.is_none_or(|(c, _, _)| cost < c) {
                best = Some((cost, axis, pos));
            }
        }
    }
    let leaf = PRIM_COST * items.len() as f32;
    best.filter(|&(c, _, _)| c < leaf || items.len() > MAX_LEAF)
        .map(|(_, a, p)| (a, p))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn finds_nearest_box_like_brute_force() {
        // Unit spheres on a line; the "primitive" test is a sphere test.
        let centers: Vec<Vec3> = (0..200)
            .map(|i| Vec3::new(i as f32 * 3.0, (i % 7) as f32, (i % 5) as f32))
            .collect();
        let bounds: Vec<(Vec3, Vec3)> = centers
            .iter()
            .map(|c| (*c - Vec3::ONE, *c + Vec3::ONE))
            .collect();
        let bvh = Bvh::build(&bounds);
        let sorted: Vec<Vec3> = bvh.order.iter().map(|&i| centers[i as usize]).collect();
        let sphere = |c: Vec3, o: Vec3, d: Vec3, s: Interval| {
            let oc = o - c;
            let b = oc.dot(d);
            let disc = b * b - (oc.length_squared() - 1.0);
            (disc >= 0.0)
                .then(|| -b - disc.sqrt())
                .filter(|t| *t > s.min && *t < s.max)
        };
        for k in 0..50 {
            let o = Vec3::new(-10.0, k as f32 * 0.13, 2.0);
            let d = Vec3::new(1.0, 0.01 * k as f32, -0.002 * k as f32).normalize();
            let span = Interval { min: 0.0, max: 1e9 };
            let got = bvh
                .intersect(o, d, span, |p, s| sphere(sorted[p as usize], o, d, s))
                .map(|h| h.0);
            let want = centers
                .iter()
                .filter_map(|c| sphere(*c, o, d, span))
                .min_by(f32::total_cmp);
            assert_eq!(got, want);
            assert_eq!(
                bvh.any(o, d, span, |p, s| sphere(sorted[p as usize], o, d, s)
                    .is_some()),
                want.is_some()
            );
        }
    }
}
