//! Tests of the SPZ writer and reader: a round trip within the quantisation steps.

use super::*;
use crate::splat::model::Gaussian;

fn random_model(n: usize, seed: u64, spread: f32) -> Gaussians {
    crate::splat::cpu::test_scenes::normal_gaussians(n, seed, |r| Gaussian {
        mean: [r() * spread, r() * spread, r() * spread],
        log_scale: [r() - 4.0, r() - 4.0, r() - 4.0],
        rotation: [r(), r(), r(), r()],
        opacity_logit: r() * 2.0,
        sh: std::array::from_fn(|k| if k < 3 { r() } else { 0.3 * r() }),
        trunk_prob: 0.5,
    })
}

fn encode(g: &Gaussians) -> Vec<u8> {
    let mut bytes = Vec::new();
    write_spz(&mut bytes, g).expect("write to memory");
    bytes
}

fn raw(bytes: &[u8]) -> Vec<u8> {
    let mut out = Vec::new();
    GzDecoder::new(bytes).read_to_end(&mut out).expect("gzip");
    out
}

#[test]
fn header_and_sizes_follow_the_format() {
    let g = random_model(10, 1, 3.0);
    let body = raw(&encode(&g));
    assert_eq!(&body[0..4], b"NGSP");
    assert_eq!(u32::from_le_bytes([body[4], body[5], body[6], body[7]]), 2);
    assert_eq!(
        u32::from_le_bytes([body[8], body[9], body[10], body[11]]),
        10
    );
    assert_eq!(&body[12..16], &[3, 12, 0, 0]);
    // 9 + 1 + 3 + 3 + 3 bytes, plus 45 SH bytes at degree 3, per Gaussian.
    assert_eq!(body.len(), 16 + 10 * (19 + 45));
    let mut d1 = g.clone();
    d1.sh_degree = 1;
    assert_eq!(raw(&encode(&d1)).len(), 16 + 10 * (19 + 9));
}

#[test]
fn round_trip_is_within_quantisation_steps() {
    for degree in [0u32, 1, 3] {
        let mut g = random_model(500, 7 + degree as u64, 20.0);
        g.sh_degree = degree;
        let back = read_spz(encode(&g).as_slice()).expect("valid SPZ");
        assert_eq!(back.len(), g.len());
        assert_eq!(back.sh_degree, degree);
        let step = 1.0 / 4096.0;
        for i in 0..g.len() {
            for a in 0..3 {
                assert!((back.means[i][a] - g.means[i][a]).abs() <= 0.5 * step + 1e-6);
                // Log-scales within ±6 of -4 sit inside the encodable range; step 1/16.
                assert!((back.log_scales[i][a] - g.log_scales[i][a]).abs() <= 1.0 / 32.0 + 1e-5);
                let dc = g.sh[i][a];
                if (dc * COLOR_SCALE + 0.5).abs() <= 1.0 && dc * COLOR_SCALE + 0.5 >= 0.0 {
                    assert!((back.sh[i][a] - dc).abs() <= 0.5 / 255.0 / COLOR_SCALE + 1e-5);
                }
            }
            let alpha = |l: f32| sigmoid(l);
            assert!(
                (alpha(back.opacity_logits[i]) - alpha(g.opacity_logits[i])).abs()
                    <= 0.5 / 255.0 + 1e-5
            );
            // Same rotation up to sign: |<q, q'>| close to 1.
            let q = g.rotations[i];
            let n = q.iter().map(|v| v * v).sum::<f32>().sqrt();
            let dot: f32 = q
                .iter()
                .zip(back.rotations[i])
                .map(|(a, b)| a / n * b)
                .sum();
            assert!(dot.abs() > 0.995, "rotation {i}: |dot| {dot}");
            for k in 0..sh_dim(degree) {
                // Rounded to 1/128, then to the bucket (8 or 16 steps): both roundings add up.
                let half = (if k < 3 { 4.0 } else { 8.0 } + 0.5) / 128.0;
                for c in 0..3 {
                    let (want, got) = (g.sh[i][3 + 3 * k + c], back.sh[i][3 + 3 * k + c]);
                    assert!(
                        (got - want.clamp(-1.0, 127.0 / 128.0)).abs() <= half + 1e-5,
                        "SH {k}/{c}: {want} -> {got}"
                    );
                }
            }
            for f in &back.sh[i][3 + 3 * sh_dim(degree)..] {
                assert_eq!(*f, 0.0);
            }
        }
    }
}

#[test]
fn large_coordinates_use_fewer_fraction_bits() {
    let mut g = random_model(3, 2, 1.0);
    g.means[1] = [5000.0, -3000.0, 1.0];
    let body = raw(&encode(&g));
    let bits = body[13];
    assert!(
        bits < 12 && 5000.0 * f32::from(1u16 << bits) < 8_388_607.0,
        "{bits}"
    );
    let back = read_spz(encode(&g).as_slice()).expect("valid");
    assert!((back.means[1][0] - 5000.0).abs() <= 1.0 / f32::from(1u16 << bits));
    // Beyond 24 bits even with no fraction: an error, not a wrapped coordinate.
    g.means[2][0] = 1e8;
    assert!(write_spz(Vec::new(), &g).is_err());
}

#[test]
fn corrupt_input_is_an_error() {
    let g = random_model(4, 3, 1.0);
    let mut body = raw(&encode(&g));
    assert!(read_spz(&b"not gzip"[..]).is_err());
    let gz = |b: &[u8]| {
        let mut e = GzEncoder::new(Vec::new(), Compression::fast());
        e.write_all(b).expect("gzip");
        e.finish().expect("gzip")
    };
    let short = gz(&body[..body.len() - 1]);
    assert!(read_spz(short.as_slice()).is_err());
    body[4] = 3;
    let v3 = gz(&body);
    let err = read_spz(v3.as_slice()).expect_err("version 3");
    assert!(err.to_string().contains("version"), "{err}");
}
