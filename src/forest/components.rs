//! Label clean-up on the k-NN graph (docs/method.md Stage 3.4): connected components of each label;
//! components smaller than tau_c points take the label of their nearest differently-labelled
//! neighbour.

/// Neighbour slots per point in a [`KnnGraph`]; unused slots hold `u32::MAX`.
pub const GRAPH_K: usize = 20;

/// The k-NN graph of a point set: for every point its nearest other points, closest first.
#[derive(Debug, Clone, Default)]
pub struct KnnGraph {
    pub neighbours: Vec<[u32; GRAPH_K]>,
}

/// Union–find with path halving and union by size.
struct DisjointSets {
    parent: Vec<u32>,
    size: Vec<u32>,
}

impl DisjointSets {
    fn new(n: usize) -> Self {
        DisjointSets {
            parent: (0..n as u32).collect(),
            size: vec![1; n],
        }
    }
    fn find(&mut self, mut a: u32) -> u32 {
        while self.parent[a as usize] != a {
            let p = self.parent[a as usize];
            self.parent[a as usize] = self.parent[p as usize];
            a = p;
        }
        a
    }
    fn union(&mut self, a: u32, b: u32) {
        let (mut a, mut b) = (self.find(a), self.find(b));
        if a == b {
            return;
        }
        if self.size[a as usize] < self.size[b as usize] {
            std::mem::swap(&mut a, &mut b);
        }
        self.parent[b as usize] = a;
        self.size[a as usize] += self.size[b as usize];
    }
}

/// Relabels small same-label components in place and returns how many points changed label.
///
/// Edges join a point to each of its graph neighbours that carries the same label (the graph
/// is used as undirected). A component with fewer than `tau_c` points takes the label of the
/// nearest differently-labelled graph neighbour of any of its points. A component without
/// any differently-labelled neighbour (an isolated fragment of the cloud) keeps its label:
/// there is no evidence to relabel it by. Relabelling is decided on the input labels, so the
/// result does not depend on the order components are visited.
pub fn relabel_small_components(labels: &mut [u8], graph: &KnnGraph, tau_c: usize) -> usize {
    let n = labels.len();
    let mut sets = DisjointSets::new(n);
    for (i, nb) in graph.neighbours.iter().enumerate().take(n) {
        for &j in nb.iter().take_while(|j| **j != u32::MAX) {
            if (j as usize) < n && labels[j as usize] == labels[i] {
                sets.union(i as u32, j);
            }
        }
    }
    let roots: Vec<u32> = (0..n as u32).map(|i| sets.find(i)).collect();
    // For each small component: the label of its nearest differently-labelled neighbour,
    // found as (rank in the neighbour list, label) minimised over its points. Graph lists
    // are sorted by distance, so the rank is a distance proxy within one point's list; across
    // points the smaller rank wins, ties by the smaller label.
    let mut best: std::collections::HashMap<u32, (usize, u8)> = Default::default();
    for i in 0..n {
        let root = roots[i];
        if (sets.size[root as usize] as usize) >= tau_c {
            continue;
        }
        let Some(nb) = graph.neighbours.get(i) else {
            continue;
        };
        if let Some((rank, &j)) = nb
            .iter()
            .take_while(|j| **j != u32::MAX)
            .enumerate()
            .find(|(_, j)| (**j as usize) < n && labels[**j as usize] != labels[i])
        {
            let cand = (rank, labels[j as usize]);
            let e = best.entry(root).or_insert(cand);
            if cand < *e {
                *e = cand;
            }
        }
    }
    let mut changed = 0;
    for i in 0..n {
        if let Some(&(_, label)) = best.get(&roots[i]) {
            labels[i] = label;
            changed += 1;
        }
    }
    changed
}

#[cfg(test)]
mod tests {
    use super::*;

    fn chain_graph(n: usize) -> KnnGraph {
        let mut neighbours = vec![[u32::MAX; GRAPH_K]; n];
        for (i, nb) in neighbours.iter_mut().enumerate() {
            let mut k = 0;
            for j in [i.wrapping_sub(1), i + 1, i.wrapping_sub(2), i + 2] {
                if j < n {
                    nb[k] = j as u32;
                    k += 1;
                }
            }
        }
        KnnGraph { neighbours }
    }

    #[test]
    fn small_islands_take_their_surroundings_label_and_large_ones_stay() {
        let mut labels = vec![0u8; 400];
        labels[100..110].fill(1); // small island: flips
        labels[200..260].fill(1); // large: stays
        let changed = relabel_small_components(&mut labels, &chain_graph(400), 50);
        assert_eq!(changed, 10);
        assert!(labels[100..110].iter().all(|l| *l == 0));
        assert!(labels[200..260].iter().all(|l| *l == 1));
    }

    #[test]
    fn isolated_fragments_keep_their_label() {
        let mut labels = vec![1u8; 10];
        let mut g = chain_graph(10);
        g.neighbours[0] = [u32::MAX; GRAPH_K];
        assert_eq!(relabel_small_components(&mut labels, &g, 50), 0);
    }
}
