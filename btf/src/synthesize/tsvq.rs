//! Tree-structured vector quantization (Wei & Levoy 2000; thesis §6.2.3), as a search
//! structure for nearest neighbourhoods.
//!
//! Each node holds the centroid of its vectors. A node is split in two along its
//! principal direction (a few power iterations started from the vector farthest from the
//! centroid) at the median projection, so the tree is balanced (depth `log₂(n/leaf)`)
//! and its construction deterministic. A query descends to the child whose centroid is
//! nearer (the TSVQ codebook walk, `O(log n)`), then searches the leaf's ≤ `leaf`
//! vectors exhaustively. The answer is approximate, as in Wei & Levoy. Nodes whose
//! vectors are all identical are not split; a query landing there gets one of them drawn
//! by the caller's random stream, so a uniform exemplar does not collapse onto one texel.

use super::SplitMix64;

enum Node {
    Split { left: usize, right: usize },
    Leaf { start: usize, end: usize, identical: bool },
}

pub struct Tsvq {
    dims: usize,
    data: Vec<f32>,
    /// Vector ids in leaf order.
    ids: Vec<u32>,
    nodes: Vec<Node>,
    /// Centroid of each node (`nodes.len() × dims`).
    centroids: Vec<f32>,
}

pub fn dist2(a: &[f32], b: &[f32]) -> f32 {
    let mut s = 0f32;
    for (x, y) in a.iter().zip(b) {
        let d = x - y;
        s += d * d;
    }
    s
}

struct Builder<'a> {
    dims: usize,
    data: &'a [f32],
    leaf: usize,
    nodes: Vec<Node>,
    centroids: Vec<f32>,
}

impl Builder<'_> {
    fn vec(&self, id: u32) -> &[f32] {
        &self.data[id as usize * self.dims..(id as usize + 1) * self.dims]
    }

    /// Build the subtree of `ids[start..end]` (reordered in place); returns its node.
    fn build(&mut self, ids: &mut [u32], start: usize) -> usize {
        let d = self.dims;
        let n = ids.len();
        let mut c = vec![0f64; d];
        for &i in ids.iter() {
            for (a, &v) in c.iter_mut().zip(self.vec(i)) {
                *a += v as f64;
            }
        }
        let centroid: Vec<f32> = c.iter().map(|&v| (v / n as f64) as f32).collect();
        let node = self.nodes.len();
        self.nodes.push(Node::Leaf {
            start,
            end: start + n,
            identical: false,
        });
        self.centroids.extend_from_slice(&centroid);
        // Farthest vector from the centroid: zero spread means all vectors are equal.
        let (far, far_d) = ids
            .iter()
            .map(|&i| (i, dist2(self.vec(i), &centroid)))
            .fold((ids[0], -1f32), |b, x| if x.1 > b.1 { x } else { b });
        if n <= self.leaf || far_d <= 0.0 {
            self.nodes[node] = Node::Leaf {
                start,
                end: start + n,
                identical: far_d <= 0.0,
            };
            return node;
        }
        let mut dir: Vec<f64> = self
            .vec(far)
            .iter()
            .zip(&centroid)
            .map(|(&a, &b)| (a - b) as f64)
            .collect();
        for _ in 0..3 {
            let mut next = vec![0f64; d];
            for &i in ids.iter() {
                let x = self.vec(i);
                let p: f64 = x
                    .iter()
                    .zip(&centroid)
                    .zip(&dir)
                    .map(|((&a, &b), &v)| (a - b) as f64 * v)
                    .sum();
                for ((o, &a), &b) in next.iter_mut().zip(x).zip(&centroid) {
                    *o += p * (a - b) as f64;
                }
            }
            let norm = next.iter().map(|v| v * v).sum::<f64>().sqrt();
            if norm <= 0.0 {
                break;
            }
            dir = next.into_iter().map(|v| v / norm).collect();
        }
        let mut keyed: Vec<(f64, u32)> = ids
            .iter()
            .map(|&i| {
                let p: f64 = self
                    .vec(i)
                    .iter()
                    .zip(&centroid)
                    .zip(&dir)
                    .map(|((&a, &b), &v)| (a - b) as f64 * v)
                    .sum();
                (p, i)
            })
            .collect();
        keyed.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        for (slot, (_, i)) in ids.iter_mut().zip(&keyed) {
            *slot = *i;
        }
        let mid = n / 2;
        let (a, b) = ids.split_at_mut(mid);
        let left = self.build(a, start);
        let right = self.build(b, start + mid);
        self.nodes[node] = Node::Split { left, right };
        node
    }
}

impl Tsvq {
    /// Build over `data.len() / dims` vectors.
    pub fn build(data: Vec<f32>, dims: usize, leaf: usize) -> Tsvq {
        let n = data.len() / dims;
        let mut ids: Vec<u32> = (0..n as u32).collect();
        let mut b = Builder {
            dims,
            data: &data,
            leaf: leaf.max(1),
            nodes: Vec::new(),
            centroids: Vec::new(),
        };
        if n > 0 {
            b.build(&mut ids, 0);
        }
        let (nodes, centroids) = (b.nodes, b.centroids);
        Tsvq {
            dims,
            data,
            ids,
            nodes,
            centroids,
        }
    }

    pub fn len(&self) -> usize {
        self.ids.len()
    }

    pub fn is_empty(&self) -> bool {
        self.ids.is_empty()
    }

    /// Vector `id` as it was given to [`Tsvq::build`].
    pub fn vector(&self, id: u32) -> &[f32] {
        &self.data[id as usize * self.dims..(id as usize + 1) * self.dims]
    }

    fn centroid(&self, node: usize) -> &[f32] {
        &self.centroids[node * self.dims..(node + 1) * self.dims]
    }

    /// Approximate nearest vector id to `q`.
    pub fn nearest(&self, q: &[f32], rng: &mut SplitMix64) -> u32 {
        let mut node = 0;
        loop {
            match self.nodes[node] {
                Node::Split { left, right } => {
                    node = if dist2(q, self.centroid(right)) < dist2(q, self.centroid(left)) {
                        right
                    } else {
                        left
                    };
                }
                Node::Leaf { start, end, identical } => {
                    if identical {
                        return self.ids[start + rng.below(end - start)];
                    }
                    let mut best = (f32::INFINITY, self.ids[start]);
                    for &i in &self.ids[start..end] {
                        let v = &self.data[i as usize * self.dims..(i as usize + 1) * self.dims];
                        let d = dist2(q, v);
                        if d < best.0 {
                            best = (d, i);
                        }
                    }
                    return best.1;
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn finds_exact_members_and_near_neighbours() {
        let mut rng = SplitMix64::new(4);
        let (n, d) = (2000, 6);
        let data: Vec<f32> = (0..n * d).map(|_| rng.unit() as f32).collect();
        let t = Tsvq::build(data.clone(), d, 8);
        let mut exact = 0;
        for i in 0..n {
            if t.nearest(&data[i * d..(i + 1) * d], &mut rng) == i as u32 {
                exact += 1;
            }
        }
        // A member is found in its own leaf unless a centroid comparison sends it astray.
        assert!(exact > n * 7 / 10, "{exact} of {n}");
        // Identical vectors: a leaf of equal members, answered without endless splitting.
        let same = Tsvq::build(vec![0.5; 300 * 4], 4, 8);
        let a = same.nearest(&[0.5; 4], &mut rng);
        assert!((a as usize) < 300);
    }
}
