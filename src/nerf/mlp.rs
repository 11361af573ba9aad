//! The NeRF network on the CPU (the reference the GPU kernels are held to): Mildenhall et al.
//! (2020)'s MLP as the paper's Section 3.7.1 gives it — `depth` ReLU layers of `width` units on
//! the encoded position, the encoded position concatenated again after layer `skip` (0-based:
//! the input of layer `skip + 1` is `[h, γ(x)]`), then a linear density, a linear feature of
//! `width`, one ReLU layer of `width / 2` on `[feature, γ(d)]` and a sigmoid colour.
//!
//! Parameters live in one flat `Vec<f32>` (what Adam and the GPU see), layer after layer, each
//! a row-major `inputs × outputs` weight matrix followed by its bias. Batches are row-major
//! `samples × features`; the products go through `matrixmultiply`'s `sgemm`.
//! Initialisation is torch's `nn.Linear` default (weights and biases uniform in ±1/√inputs),
//! seeded.

use crate::geom::gemm;
use crate::rng::SplitMix64;

/// Sizes of the network.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct MlpShape {
    /// ReLU layers on the position: 8 (the paper).
    pub depth: usize,
    /// Units per layer: 256 (the paper).
    pub width: usize,
    /// The encoded position joins again after this layer (0-based): 4 (the paper's skip at
    /// the 4th layer, Mildenhall's `skips=[4]`).
    pub skip: usize,
    /// Encoded position floats: 3 + 6 × bands.
    pub pos_dim: usize,
    /// Encoded direction floats: 3 + 6 × bands.
    pub dir_dim: usize,
}

/// Where one layer's parameters are in the flat vector.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Layer {
    pub inputs: usize,
    pub outputs: usize,
    /// Offset of the weights (`inputs × outputs`, row-major); the bias follows them.
    pub offset: usize,
}

impl Layer {
    pub fn bias_offset(&self) -> usize {
        self.offset + self.inputs * self.outputs
    }
    pub fn end(&self) -> usize {
        self.bias_offset() + self.outputs
    }
}

/// The network: its shape, layers and parameters.
#[derive(Debug, Clone)]
pub struct Mlp {
    pub shape: MlpShape,
    /// Trunk layers `0..depth`, then density, feature, view and colour.
    pub layers: Vec<Layer>,
    pub params: Vec<f32>,
}

/// What a forward pass keeps for its backward pass: each layer's input and output (after its
/// activation), samples × features.
#[derive(Debug, Default)]
pub struct Cache {
    inputs: Vec<Vec<f32>>,
    outputs: Vec<Vec<f32>>,
    n: usize,
}

/// Density before its ReLU and colour after its sigmoid, per sample.
#[derive(Debug, Clone, Default)]
pub struct Output {
    pub sigma_raw: Vec<f32>,
    pub rgb: Vec<[f32; 3]>,
}

impl Mlp {
    /// A freshly initialised network.
    pub fn new(shape: MlpShape, seed: u64) -> Self {
        let mut sizes = Vec::new();
        for l in 0..shape.depth {
            let inputs = if l == 0 {
                shape.pos_dim
            } else if l == shape.skip + 1 {
                shape.width + shape.pos_dim
            } else {
                shape.width
            };
            sizes.push((inputs, shape.width));
        }
        sizes.push((shape.width, 1));
        sizes.push((shape.width, shape.width));
        sizes.push((shape.width + shape.dir_dim, shape.width / 2));
        sizes.push((shape.width / 2, 3));
        let mut layers = Vec::new();
        let mut offset = 0;
        for (inputs, outputs) in sizes {
            let l = Layer {
                inputs,
                outputs,
                offset,
            };
            offset = l.end();
            layers.push(l);
        }
        let mut rng = SplitMix64::new(seed);
        let mut params = vec![0.0f32; offset];
        for l in &layers {
            let bound = 1.0 / (l.inputs as f64).sqrt();
            for p in &mut params[l.offset..l.end()] {
                *p = ((rng.uniform() * 2.0 - 1.0) * bound) as f32;
            }
        }
        Mlp {
            shape,
            layers,
            params,
        }
    }

    fn density_layer(&self) -> usize {
        self.shape.depth
    }

    /// Density and colour of `n` samples from their encoded positions (`n × pos_dim`) and
    /// directions (`n × dir_dim`); with `cache`, what [`Mlp::backward`] needs.
    pub fn forward(
        &self,
        pos: &[f32],
        dir: &[f32],
        n: usize,
        mut cache: Option<&mut Cache>,
    ) -> Output {
        let s = self.shape;
        debug_assert_eq!(pos.len(), n * s.pos_dim);
        debug_assert_eq!(dir.len(), n * s.dir_dim);
        if let Some(c) = cache.as_deref_mut() {
            c.inputs.clear();
            c.outputs.clear();
        }
        let mut keep = |input: Vec<f32>, output: &Vec<f32>| {
            if let Some(c) = cache.as_deref_mut() {
                c.inputs.push(input);
                c.outputs.push(output.clone());
            }
        };
        let mut h = pos.to_vec();
        for l in 0..s.depth {
            let input = if l == s.skip + 1 {
                concat(&h, s.width, pos, s.pos_dim, n)
            } else {
                h
            };
            let mut out = dense(&self.params, &self.layers[l], &input, n);
            relu(&mut out);
            keep(input, &out);
            h = out;
        }
        let sigma_raw = dense(&self.params, &self.layers[s.depth], &h, n);
        let feature = dense(&self.params, &self.layers[s.depth + 1], &h, n);
        keep(h.clone(), &sigma_raw);
        keep(h, &feature);
        let view_in = concat(&feature, s.width, dir, s.dir_dim, n);
        let mut view = dense(&self.params, &self.layers[s.depth + 2], &view_in, n);
        relu(&mut view);
        keep(view_in, &view);
        let mut rgb = dense(&self.params, &self.layers[s.depth + 3], &view, n);
        for v in &mut rgb {
            *v = sigmoid(*v);
        }
        keep(view, &rgb);
        if let Some(c) = cache {
            c.n = n;
        }
        Output {
            sigma_raw,
            rgb: rgb.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect(),
        }
    }

    /// Adds to `grad` (as long as `params`) the gradient of a loss whose derivatives by each
    /// sample's raw density and colour are `d_sigma_raw` and `d_rgb`, through the pass that
    /// filled `cache`.
    pub fn backward(
        &self,
        cache: &Cache,
        d_sigma_raw: &[f32],
        d_rgb: &[[f32; 3]],
        grad: &mut [f32],
    ) {
        let s = self.shape;
        let n = cache.n;
        let last = s.depth + 3;
        // Colour: through the sigmoid.
        let rgb = &cache.outputs[last];
        let d_rgb_raw: Vec<f32> = d_rgb
            .iter()
            .flatten()
            .zip(rgb)
            .map(|(d, y)| d * y * (1.0 - y))
            .collect();
        let mut d_view = dense_back(
            &self.params,
            &self.layers[last],
            &cache.inputs[last],
            &d_rgb_raw,
            n,
            grad,
        );
        relu_back(&mut d_view, &cache.outputs[s.depth + 2]);
        let d_view_in = dense_back(
            &self.params,
            &self.layers[s.depth + 2],
            &cache.inputs[s.depth + 2],
            &d_view,
            n,
            grad,
        );
        let d_feature = split(&d_view_in, s.width + s.dir_dim, s.width, n);
        let mut d_h = dense_back(
            &self.params,
            &self.layers[s.depth + 1],
            &cache.inputs[s.depth + 1],
            &d_feature,
            n,
            grad,
        );
        let d_h_sigma = dense_back(
            &self.params,
            &self.layers[self.density_layer()],
            &cache.inputs[s.depth],
            d_sigma_raw,
            n,
            grad,
        );
        for (a, b) in d_h.iter_mut().zip(&d_h_sigma) {
            *a += b;
        }
        for l in (0..s.depth).rev() {
            relu_back(&mut d_h, &cache.outputs[l]);
            if l == 0 {
                dense_back_weights(&self.layers[0], &cache.inputs[0], &d_h, n, grad);
                break;
            }
            let d_in = dense_back(
                &self.params,
                &self.layers[l],
                &cache.inputs[l],
                &d_h,
                n,
                grad,
            );
            d_h = if l == s.skip + 1 {
                split(&d_in, s.width + s.pos_dim, s.width, n)
            } else {
                d_in
            };
        }
    }
}

pub fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}

fn relu(v: &mut [f32]) {
    for x in v {
        *x = x.max(0.0);
    }
}

/// Zeroes the gradient where the ReLU's output was 0.
fn relu_back(d: &mut [f32], out: &[f32]) {
    for (g, y) in d.iter_mut().zip(out) {
        if *y <= 0.0 {
            *g = 0.0;
        }
    }
}

/// Rows `[a, b]` of `n` samples.
fn concat(a: &[f32], wa: usize, b: &[f32], wb: usize, n: usize) -> Vec<f32> {
    let mut out = Vec::with_capacity(n * (wa + wb));
    for i in 0..n {
        out.extend_from_slice(&a[i * wa..(i + 1) * wa]);
        out.extend_from_slice(&b[i * wb..(i + 1) * wb]);
    }
    out
}

/// The first `keep` columns of rows `w` wide.
fn split(a: &[f32], w: usize, keep: usize, n: usize) -> Vec<f32> {
    let mut out = Vec::with_capacity(n * keep);
    for i in 0..n {
        out.extend_from_slice(&a[i * w..i * w + keep]);
    }
    out
}

/// `x W + b` for `n` rows.
fn dense(params: &[f32], l: &Layer, x: &[f32], n: usize) -> Vec<f32> {
    let mut y = Vec::with_capacity(n * l.outputs);
    let b = &params[l.bias_offset()..l.end()];
    for _ in 0..n {
        y.extend_from_slice(b);
    }
    gemm(
        n,
        l.inputs,
        l.outputs,
        (x, l.inputs as isize, 1),
        (&params[l.offset..], l.outputs as isize, 1),
        &mut y,
    );
    y
}

/// Adds `xᵀ dy` and the column sums of `dy` to the layer's gradient; returns `dy Wᵀ`.
fn dense_back(
    params: &[f32],
    l: &Layer,
    x: &[f32],
    dy: &[f32],
    n: usize,
    grad: &mut [f32],
) -> Vec<f32> {
    dense_back_weights(l, x, dy, n, grad);
    let mut dx = vec![0.0f32; n * l.inputs];
    // B = Wᵀ: element (k, j) = W[j][k], so row stride 1 and column stride `outputs`.
    gemm(
        n,
        l.outputs,
        l.inputs,
        (dy, l.outputs as isize, 1),
        (&params[l.offset..], 1, l.outputs as isize),
        &mut dx,
    );
    dx
}

fn dense_back_weights(l: &Layer, x: &[f32], dy: &[f32], n: usize, grad: &mut [f32]) {
    // A = xᵀ (inputs × n): element (i, s) = x[s][i].
    let (w, b) = grad[l.offset..l.end()].split_at_mut(l.inputs * l.outputs);
    gemm(
        l.inputs,
        n,
        l.outputs,
        (x, 1, l.inputs as isize),
        (dy, l.outputs as isize, 1),
        w,
    );
    for row in dy.chunks_exact(l.outputs) {
        for (g, d) in b.iter_mut().zip(row) {
            *g += d;
        }
    }
}
