//! Consistent normal orientation by a minimum-spanning-tree walk over the k-NN graph
//! (Hoppe et al. 1992): edge weight 1 - |n_i · n_j|, each newly reached normal flipped to
//! agree with the one it was reached from. Weights are bucketed into [`BUCKETS`] levels so
//! the walk is linear-time; within a bucket the order is last-in-first-out.

use glam::Vec3;
use rayon::prelude::*;

use super::GeomError;
use crate::progress::Progress;

/// Neighbours per point kept for the orientation graph (the point itself not counted).
/// Eight keeps the graph connected on TLS-like clouds at 32 bytes per point.
pub(super) const GRAPH_K: usize = 8;
/// Priority levels of the bucketed minimum-spanning-tree walk.
const BUCKETS: usize = 32;

/// Orients `normals` consistently by a bucketed minimum-spanning-tree walk over `graph`.
pub(super) fn propagate(
    normals: &mut [Vec3],
    graph: &[[u32; GRAPH_K]],
    up: Vec3,
    progress: &dyn Progress,
) -> Result<(), GeomError> {
    let n = normals.len();
    if n == 0 {
        return Ok(());
    }
    let mut visited = vec![false; n];
    let mut buckets: Vec<Vec<(u32, u32)>> = vec![Vec::new(); BUCKETS];
    let first = (0..n)
        .into_par_iter()
        .max_by(|&a, &b| {
            normals[a]
                .dot(up)
                .abs()
                .total_cmp(&normals[b].dot(up).abs())
        })
        .unwrap_or(0);
    let mut done = 0usize;
    for s in std::iter::once(first).chain(0..n) {
        if visited[s] {
            continue;
        }
        // A new tree: agree with the best-aligned already oriented neighbour, else with up.
        let reference = graph[s]
            .iter()
            .filter(|&&j| j != u32::MAX && visited[j as usize])
            .map(|&j| normals[j as usize])
            .max_by(|a, b| a.dot(normals[s]).abs().total_cmp(&b.dot(normals[s]).abs()))
            .unwrap_or(up);
        if normals[s].dot(reference) < 0.0 {
            normals[s] = -normals[s];
        }
        visited[s] = true;
        done += 1;
        let mut lowest = BUCKETS;
        push_edges(s, normals, graph, &visited, &mut buckets, &mut lowest);
        while lowest < BUCKETS {
            let Some((j, parent)) = buckets[lowest].pop() else {
                lowest += 1;
                continue;
            };
            let j = j as usize;
            if visited[j] {
                continue;
            }
            if normals[j].dot(normals[parent as usize]) < 0.0 {
                normals[j] = -normals[j];
            }
            visited[j] = true;
            done += 1;
            if done.is_multiple_of(1 << 20) {
                if progress.is_cancelled() {
                    return Err(GeomError::Cancelled);
                }
                progress.set(done as f64 / n as f64);
            }
            push_edges(j, normals, graph, &visited, &mut buckets, &mut lowest);
        }
    }
    progress.set(1.0);
    Ok(())
}

fn push_edges(
    i: usize,
    normals: &[Vec3],
    graph: &[[u32; GRAPH_K]],
    visited: &[bool],
    buckets: &mut [Vec<(u32, u32)>],
    lowest: &mut usize,
) {
    let ni = normals[i];
    for &j in &graph[i] {
        if j == u32::MAX || visited[j as usize] {
            continue;
        }
        let w = 1.0 - ni.dot(normals[j as usize]).abs();
        let b = ((w * BUCKETS as f32) as usize).min(BUCKETS - 1);
        buckets[b].push((j, i as u32));
        *lowest = (*lowest).min(b);
    }
}
