//! Tests of the glTF writer and reader: the layout the extension specifies, the GLB framing,
//! and a round trip to float precision.

use super::*;
use crate::splat::model::Gaussian;

fn random_model(n: usize, seed: u64, degree: u32) -> Gaussians {
    let mut g = crate::splat::cpu::test_scenes::normal_gaussians(n, seed, |r| Gaussian {
        mean: [r() * 20.0, r() * 20.0, r() * 5.0 + 10.0],
        log_scale: [r() - 4.0, r() - 4.0, r() - 4.0],
        rotation: [r(), r(), r(), r()],
        opacity_logit: r() * 2.0,
        sh: std::array::from_fn(|k| if k < 3 { r() } else { 0.3 * r() }),
        trunk_prob: 0.5 + 0.4 * r().clamp(-1.0, 1.0),
    });
    g.sh_degree = degree;
    g
}

fn encode(g: &Gaussians) -> Vec<u8> {
    let mut bytes = Vec::new();
    write_glb(&mut bytes, g).expect("write to memory");
    bytes
}

#[test]
fn the_glb_is_framed_and_aligned_as_gltf_says() {
    let g = random_model(7, 1, 1);
    let bytes = encode(&g);
    assert_eq!(&bytes[0..4], b"glTF");
    assert_eq!(u32::from_le_bytes(bytes[4..8].try_into().expect("4")), 2);
    let total = u32::from_le_bytes(bytes[8..12].try_into().expect("4")) as usize;
    assert_eq!(total, bytes.len());
    let json_len = u32::from_le_bytes(bytes[12..16].try_into().expect("4")) as usize;
    assert_eq!(&bytes[16..20], b"JSON");
    assert_eq!(json_len % 4, 0);
    let bin_at = 20 + json_len;
    assert_eq!(&bytes[bin_at + 4..bin_at + 8], b"BIN\0");
    assert_eq!(total % 4, 0);
}

#[test]
fn the_primitive_carries_the_extension_s_attributes() {
    let g = random_model(5, 2, 2);
    let (doc, bin) = read_glb_parts(encode(&g).as_slice()).expect("parts");
    assert_eq!(doc["extensionsUsed"], json!([EXTENSION]));
    assert!(
        doc.get("extensionsRequired").is_none(),
        "points are the fallback"
    );
    let prim = &doc["meshes"][0]["primitives"][0];
    assert_eq!(prim["mode"], 0);
    let ext = &prim["extensions"][EXTENSION];
    assert_eq!(ext["kernel"], "ellipse");
    assert_eq!(ext["colorSpace"], "srgb_rec709_display");
    let attrs = prim["attributes"].as_object().expect("attributes");
    let mut want = vec![
        "POSITION".to_string(),
        format!("{EXTENSION}:ROTATION"),
        format!("{EXTENSION}:SCALE"),
        format!("{EXTENSION}:OPACITY"),
        "COLOR_0".into(),
        "_TRUNK_PROB".into(),
    ];
    // Degree 2: 1 + 3 + 5 coefficients, and none of degree 3.
    for l in 0..=2 {
        want.extend((0..=2 * l).map(|n| sh_semantic(l, n)));
    }
    let mut got: Vec<String> = attrs.keys().cloned().collect();
    got.sort();
    want.sort();
    assert_eq!(got, want);
    for (semantic, index) in attrs {
        let acc = &doc["accessors"][index.as_u64().expect("index") as usize];
        assert_eq!(acc["count"], 5, "{semantic}");
        let view = &doc["bufferViews"][acc["bufferView"].as_u64().expect("view") as usize];
        assert_eq!(
            view["byteOffset"].as_u64().expect("offset") % 4,
            0,
            "{semantic}"
        );
    }
    let pos = &doc["accessors"][attrs["POSITION"].as_u64().expect("index") as usize];
    let lo = g.means.iter().map(|m| m[0]).fold(f32::INFINITY, f32::min);
    assert_eq!(pos["min"][0].as_f64(), Some(f64::from(lo)));
    assert_eq!(
        doc["buffers"][0]["byteLength"].as_u64(),
        Some(bin.len() as u64)
    );
    // The node turns the model's z up into glTF's y up.
    assert_eq!(doc["nodes"][0]["matrix"], json!(Z_UP_TO_Y_UP));
}

#[test]
fn a_round_trip_keeps_the_model_to_float_precision() {
    for degree in [0, 3] {
        let g = random_model(200, 3 + u64::from(degree), degree);
        let back = read_glb(encode(&g).as_slice()).expect("read");
        assert_eq!(back.len(), g.len());
        assert_eq!(back.sh_degree, degree);
        assert_eq!(back.means, g.means);
        assert_eq!(back.trunk_prob, g.trunk_prob);
        let coefs = crate::splat::model::sh_coeffs_for_degree(degree) * 3;
        for i in 0..g.len() {
            assert_eq!(back.sh[i][..coefs], g.sh[i][..coefs]);
            assert!(back.sh[i][coefs..].iter().all(|&v| v == 0.0));
            for k in 0..3 {
                let (a, b) = (back.log_scales[i][k], g.log_scales[i][k]);
                assert!((a - b).abs() < 1e-5, "log scale {a} vs {b}");
            }
            let (a, b) = (back.opacity_logits[i], g.opacity_logits[i]);
            assert!(
                (a - b).abs() < 1e-4 * (1.0 + b.abs()),
                "opacity logit {a} vs {b}"
            );
            // The same rotation: unit quaternions equal up to sign.
            let q = g.rotations[i];
            let n = q.iter().map(|v| v * v).sum::<f32>().sqrt();
            let dot: f32 = (0..4).map(|k| back.rotations[i][k] * q[k] / n).sum();
            assert!((dot.abs() - 1.0).abs() < 1e-6, "rotation dot {dot}");
        }
    }
}

#[test]
fn the_fallback_colour_is_the_linear_diffuse_colour_and_opacity() {
    let mut g = random_model(1, 4, 0);
    // DC giving sRGB 0.5 in red (linear 0.214), 1 in green, 0 in blue; opacity 0.5.
    g.sh[0][0] = 0.0;
    g.sh[0][1] = 0.5 / SH_C0;
    g.sh[0][2] = -0.5 / SH_C0;
    g.opacity_logits[0] = 0.0;
    let (doc, bin) = read_glb_parts(encode(&g).as_slice()).expect("parts");
    let index = doc["meshes"][0]["primitives"][0]["attributes"]["COLOR_0"]
        .as_u64()
        .expect("colour");
    let acc = &doc["accessors"][index as usize];
    assert_eq!(acc["componentType"], UNSIGNED_BYTE);
    assert_eq!(acc["normalized"], true);
    let at = doc["bufferViews"][acc["bufferView"].as_u64().expect("view") as usize]["byteOffset"]
        .as_u64()
        .expect("offset") as usize;
    assert_eq!(&bin[at..at + 4], &[55, 255, 0, 128]);
}

#[test]
fn what_is_not_a_splat_glb_is_refused_with_the_reason() {
    assert!(matches!(read_glb(&b"ply\n"[..]), Err(GlbError::NotGlb)));
    let (mut doc, bin) = read_glb_parts(encode(&random_model(3, 5, 0)).as_slice()).expect("ok");
    doc["meshes"][0]["primitives"][0]["extensions"] = json!({});
    let mut bytes = Vec::new();
    write_glb_parts(&mut bytes, &doc, &bin).expect("write");
    let err = read_glb(bytes.as_slice()).expect_err("no splats");
    assert!(err.to_string().contains(EXTENSION), "{err}");
    let truncated = &encode(&random_model(3, 5, 0))[..40];
    assert!(read_glb(truncated).is_err());
}

#[test]
fn the_half_turn_is_its_own_inverse_and_keeps_each_splat_s_look() {
    let g = random_model(20, 6, 3);
    let turned = half_turn_y(&g);
    assert_eq!(half_turn_y(&turned), g);
    // Seen along the turned direction, each turned splat has the colour the original has.
    for i in 0..g.len() {
        for d in [[0.6f64, -0.3, 0.74], [-0.2, 0.9, 0.38], [0.0, 0.0, 1.0]] {
            let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
            let d = [d[0] / n, d[1] / n, d[2] / n];
            let a = crate::splat::cpu::sh::eval_sh(3, &g.sh[i], d);
            let b = crate::splat::cpu::sh::eval_sh(3, &turned.sh[i], [-d[0], d[1], -d[2]]);
            for c in 0..3 {
                assert!(
                    (a[c] - b[c]).abs() < 1e-5,
                    "splat {i} {d:?}: {a:?} vs {b:?}"
                );
            }
        }
        // And the same covariance, turned: R' S² R'ᵀ = F R S² Rᵀ F.
        let cov = |q: [f32; 4], s: [f32; 3]| {
            let r =
                glam::Mat3::from_quat(glam::Quat::from_xyzw(q[1], q[2], q[3], q[0]).normalize());
            let s = glam::Mat3::from_diagonal(glam::Vec3::from_array(s.map(|v| (2.0 * v).exp())));
            r * s * r.transpose()
        };
        let f = glam::Mat3::from_diagonal(glam::Vec3::new(-1.0, 1.0, -1.0));
        let want = f * cov(g.rotations[i], g.log_scales[i]) * f;
        let got = cov(turned.rotations[i], turned.log_scales[i]);
        assert!(want.abs_diff_eq(got, 1e-9), "{want} vs {got}");
    }
}

#[test]
fn an_spz_compressed_glb_names_its_stream_and_reads_back_within_its_steps() {
    let g = random_model(300, 7, 1);
    let mut bytes = Vec::new();
    write_glb_spz(&mut bytes, &g).expect("write");
    let (doc, bin) = read_glb_parts(bytes.as_slice()).expect("parts");
    assert_eq!(doc["extensionsRequired"], json!([EXTENSION, SPZ_EXTENSION]));
    let prim = &doc["meshes"][0]["primitives"][0];
    assert_eq!(
        prim["extensions"][EXTENSION]["extensions"][SPZ_EXTENSION]["bufferView"],
        0
    );
    let attrs = prim["attributes"].as_object().expect("attributes");
    // Degree 1: three SH coefficients; opacity and DC ride in COLOR_0.
    assert_eq!(attrs.len(), 4 + 3, "{attrs:?}");
    assert!(attrs.get(&format!("{EXTENSION}:OPACITY")).is_none());
    for index in attrs.values() {
        let acc = &doc["accessors"][index.as_u64().expect("index") as usize];
        assert!(acc.get("bufferView").is_none());
        assert_eq!(acc["count"], 300);
    }
    // The stream is SPZ (gzip) of the half-turned model.
    let len = doc["bufferViews"][0]["byteLength"].as_u64().expect("len") as usize;
    let direct = crate::splat::export_spz::read_spz(&bin[..len]).expect("spz");
    assert!((direct.means[0][0] + g.means[0][0]).abs() < 1e-3);
    let back = read_glb(bytes.as_slice()).expect("read");
    assert_eq!(back.len(), g.len());
    assert_eq!(back.sh_degree, 1);
    for i in 0..g.len() {
        for k in 0..3 {
            // 12 fraction bits: 0.24 mm steps.
            assert!((back.means[i][k] - g.means[i][k]).abs() < 2.5e-4);
            // Log-scales in steps of 1/16.
            assert!((back.log_scales[i][k] - g.log_scales[i][k]).abs() <= 1.0 / 32.0 + 1e-6);
        }
        // DC within the colour byte's step (1 / (0.15 · 255)) of its range (±0.5 / 0.15);
        // degree 1 within its 5-bit bucket.
        for c in 0..3 {
            let dc = g.sh[i][c].clamp(-0.5 / 0.15, 0.5 / 0.15);
            assert!((back.sh[i][c] - dc).abs() < 0.014, "dc {i}");
            let sh1 = g.sh[i][3 + c].clamp(-1.0, 127.0 / 128.0);
            assert!(
                (back.sh[i][3 + c] - sh1).abs() < 0.04,
                "sh1 {i}: {} vs {sh1}",
                back.sh[i][3 + c]
            );
        }
    }
}
