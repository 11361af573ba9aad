//! CPU reference of the exposure kernels (`shaders/exposure.wgsl`; docs/splatting.md
//! "Exposure"), in f64: the per-image affine transform `out = A · rgb + b` of a rendered image
//! and its backward. `e` is the image's `[A | b]`, row-major 3×4
//! ([`crate::splat::exposure`]).
//!
//! With `left_half` (a held-out view's training step) the pixels of columns `x ≥ width / 2`
//! are replaced by the photo: they carry no gradient, to the transform or to the render.

/// Whether pixel `i` of an image `width` wide lies in the right half (`x ≥ width / 2`).
pub fn in_right_half(i: usize, width: usize) -> bool {
    i % width.max(1) >= width / 2
}

/// `A · rgb + b` for one pixel.
fn transform(e: &[f64; 12], c: [f64; 3]) -> [f64; 3] {
    std::array::from_fn(|r| {
        e[4 * r] * c[0] + e[4 * r + 1] * c[1] + e[4 * r + 2] * c[2] + e[4 * r + 3]
    })
}

/// The exposed image: `A · rgb + b` per pixel of `image` (row-major, `width` wide); with
/// `right_target = Some(target)` the right-half pixels take the target's value instead.
pub fn apply(
    image: &[[f64; 3]],
    e: &[f64; 12],
    width: usize,
    right_target: Option<&[[f64; 3]]>,
) -> Vec<[f64; 3]> {
    image
        .iter()
        .enumerate()
        .map(|(i, &c)| match right_target {
            Some(t) if in_right_half(i, width) => t[i],
            _ => transform(e, c),
        })
        .collect()
}

/// Backward of [`apply`]: given dL/dout per pixel, returns dL/drgb (`Aᵀ · dL/dout`, zero on the
/// replaced pixels when `left_half`) and dL/d`e` (`dL/da_rc = Σ dL/dout_r · rgb_c`,
/// `dL/db_r = Σ dL/dout_r` over the pixels that were transformed).
pub fn backward(
    image: &[[f64; 3]],
    e: &[f64; 12],
    dl_dout: &[[f64; 3]],
    width: usize,
    left_half: bool,
) -> (Vec<[f64; 3]>, [f64; 12]) {
    let mut de = [0.0; 12];
    let dl_drgb = image
        .iter()
        .zip(dl_dout)
        .enumerate()
        .map(|(i, (&c, &g))| {
            if left_half && in_right_half(i, width) {
                return [0.0; 3];
            }
            for r in 0..3 {
                for k in 0..3 {
                    de[4 * r + k] += g[r] * c[k];
                }
                de[4 * r + 3] += g[r];
            }
            std::array::from_fn(|k| (0..3).map(|r| e[4 * r + k] * g[r]).sum())
        })
        .collect();
    (dl_drgb, de)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::SplitMix64;
    use crate::splat::cpu::loss_and_grad_f64;

    const W: usize = 23;
    const H: usize = 17;

    fn random_image(rng: &mut SplitMix64) -> Vec<[f64; 3]> {
        (0..W * H)
            .map(|_| [0, 1, 2].map(|_| 0.1 + 0.8 * rng.uniform()))
            .collect()
    }

    /// A transform away from the identity: gains 0.7–1.3, small cross terms and offsets.
    fn random_exposure(rng: &mut SplitMix64) -> [f64; 12] {
        let mut e = [0.0; 12];
        for r in 0..3 {
            for k in 0..4 {
                e[4 * r + k] = if k == r {
                    0.7 + 0.6 * rng.uniform()
                } else {
                    0.1 * (rng.uniform() - 0.5)
                };
            }
        }
        e
    }

    fn loss(image: &[[f64; 3]], e: &[f64; 12], target: &[[f64; 3]], left_half: bool) -> f64 {
        let out = apply(image, e, W, left_half.then_some(target));
        loss_and_grad_f64(&out, target, W as u32, H as u32)
            .expect("sizes")
            .0
            .loss
    }

    /// The analytic dL/de and dL/drgb of the training loss through [`apply`] against central
    /// differences, for a plain and a held-out (left-half) step.
    #[test]
    fn exposure_backward_matches_finite_differences() {
        let mut rng = SplitMix64::new(11);
        for left_half in [false, true] {
            let image = random_image(&mut rng);
            let target = random_image(&mut rng);
            let e = random_exposure(&mut rng);
            let out = apply(&image, &e, W, left_half.then_some(&target[..]));
            let (_, dl_dout) = loss_and_grad_f64(&out, &target, W as u32, H as u32).expect("sizes");
            let (dl_drgb, de) = backward(&image, &e, &dl_dout, W, left_half);
            let h = 1e-6;
            let scale = de.iter().fold(0.0f64, |m, v| m.max(v.abs()));
            assert!(scale > 1e-4, "dL/de vanishes: the check would be vacuous");
            for k in 0..12 {
                let (mut ep, mut em) = (e, e);
                ep[k] += h;
                em[k] -= h;
                let fd = (loss(&image, &ep, &target, left_half)
                    - loss(&image, &em, &target, left_half))
                    / (2.0 * h);
                assert!(
                    (fd - de[k]).abs() <= 1e-6 * scale + 1e-4 * fd.abs(),
                    "left_half {left_half}, dL/de[{k}]: analytic {} vs FD {fd}",
                    de[k]
                );
            }
            let gscale = dl_drgb.iter().flatten().fold(0.0f64, |m, v| m.max(v.abs()));
            let mut checked_right = 0;
            for i in (0..W * H).step_by(7) {
                for c in 0..3 {
                    let (mut ip, mut im) = (image.clone(), image.clone());
                    ip[i][c] += h;
                    im[i][c] -= h;
                    let fd = (loss(&ip, &e, &target, left_half)
                        - loss(&im, &e, &target, left_half))
                        / (2.0 * h);
                    assert!(
                        (fd - dl_drgb[i][c]).abs() <= 1e-5 * gscale + 1e-4 * fd.abs(),
                        "left_half {left_half}, pixel {i} channel {c}: analytic {} vs FD {fd}",
                        dl_drgb[i][c]
                    );
                    if left_half && in_right_half(i, W) {
                        assert_eq!(dl_drgb[i][c], 0.0);
                        checked_right += 1;
                    }
                }
            }
            assert_eq!(left_half, checked_right > 0);
        }
    }

    #[test]
    fn the_identity_leaves_the_image_and_the_right_half_takes_the_target() {
        let mut rng = SplitMix64::new(3);
        let image = random_image(&mut rng);
        let target = random_image(&mut rng);
        let id = crate::splat::exposure::IDENTITY.map(f64::from);
        assert_eq!(apply(&image, &id, W, None), image);
        let half = apply(&image, &id, W, Some(&target));
        for (i, p) in half.iter().enumerate() {
            let want = if i % W >= W / 2 { target[i] } else { image[i] };
            assert_eq!(*p, want);
        }
    }
}
