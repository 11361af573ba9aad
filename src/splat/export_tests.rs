//! Tests of the INRIA PLY writer and reader.

use super::*;
use crate::splat::model::{Gaussian, SH_FLOATS};

fn random_model(n: usize, seed: u64) -> Gaussians {
    crate::splat::cpu::test_scenes::normal_gaussians(n, seed, |r| Gaussian {
        mean: [r(), r(), r()],
        log_scale: [r(), r(), r()],
        rotation: [r(), r(), r(), r()],
        opacity_logit: r(),
        sh: std::array::from_fn(|_| r()),
        trunk_prob: r().abs().min(1.0),
    })
}

fn header_of(bytes: &[u8]) -> String {
    let end = find_end_header(bytes).expect("header");
    String::from_utf8_lossy(&bytes[..end]).into_owned()
}

#[test]
fn ply_round_trip_preserves_every_parameter() {
    let g = random_model(7, 5);
    let mut bytes = Vec::new();
    write_ply_with(&mut bytes, &g, true).expect("write to memory");
    assert_eq!(read_ply(bytes.as_slice()).expect("valid PLY"), g);
    // The exact INRIA layout drops the trunk probability.
    let mut plain = Vec::new();
    write_ply(&mut plain, &g).expect("write to memory");
    let back = read_ply(plain.as_slice()).expect("valid PLY");
    assert_eq!((back.sh, back.means), (g.sh.clone(), g.means.clone()));
    assert!(back.trunk_prob.iter().all(|&p| p == 0.0));
}

#[test]
fn ply_header_lists_exactly_the_inria_properties() {
    let mut bytes = Vec::new();
    write_ply(&mut bytes, &random_model(2, 1)).expect("write");
    let header = header_of(&bytes);
    let props: Vec<&str> = header
        .lines()
        .filter_map(|l| l.strip_prefix("property float "))
        .collect();
    assert_eq!(props.len(), 62);
    assert_eq!(
        &props[..9],
        &[
            "x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"
        ]
    );
    assert_eq!(props[9 + 44], "f_rest_44");
    assert_eq!(
        &props[54..],
        &[
            "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"
        ]
    );
    assert!(header.starts_with("ply\nformat binary_little_endian 1.0\nelement vertex 2\n"));
    assert_eq!(bytes.len() - header.len(), 2 * 62 * 4);
}

#[test]
fn f_rest_is_channel_major() {
    let mut g = Gaussians::default();
    let mut one = Gaussian::isotropic([0.0; 3], 1.0, [0.5; 3], 0.5);
    one.sh = [0.0; SH_FLOATS];
    one.sh[3 + 1] = 7.0; // k = 1, green
    one.sh[15 * 3 + 2] = 9.0; // k = 15, blue
    g.push(one);
    let mut bytes = Vec::new();
    write_ply(&mut bytes, &g).expect("write");
    let data = &bytes[header_of(&bytes).len()..];
    let f =
        |prop: usize| f32::from_le_bytes(data[prop * 4..prop * 4 + 4].try_into().expect("4 bytes"));
    // f_rest_j sits at property 9 + j; green k = 1 is j = 15, blue k = 15 is j = 44.
    assert_eq!(f(9 + 15), 7.0);
    assert_eq!(f(9 + 44), 9.0);
    assert_eq!((0..45).filter(|&j| f(9 + j) != 0.0).count(), 2);
}

#[test]
fn reader_explains_missing_properties_and_truncation() {
    let mut bytes = Vec::new();
    write_ply(&mut bytes, &random_model(3, 2)).expect("write");
    let err = read_ply(&bytes[..bytes.len() - 10]).expect_err("truncated");
    assert!(
        matches!(err, PlyError::Truncated { vertices: 3, .. }),
        "{err}"
    );
    let renamed = String::from_utf8_lossy(&bytes).replacen(
        "property float opacity",
        "property float opacitx",
        1,
    );
    let err = read_ply(renamed.as_bytes()).expect_err("missing opacity");
    assert!(err.to_string().contains("\"opacity\""), "{err}");
    let ascii = b"ply\nformat ascii 1.0\nelement vertex 0\nend_header\n";
    assert!(matches!(
        read_ply(&ascii[..]),
        Err(PlyError::UnsupportedFormat(_))
    ));
    assert!(matches!(
        read_ply(&b"PK\x03\x04"[..]),
        Err(PlyError::NotPly)
    ));
}

#[test]
fn reader_accepts_degree_zero_files() {
    let mut text = String::from("ply\nformat binary_little_endian 1.0\nelement vertex 1\n");
    let names = [
        "x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
    ];
    for n in names.iter().chain(&["rot_0", "rot_1", "rot_2", "rot_3"]) {
        text += &format!("property float {n}\n");
    }
    text += "end_header\n";
    let mut bytes = text.into_bytes();
    for v in 0..14 {
        bytes.extend_from_slice(&(v as f32).to_le_bytes());
    }
    let g = read_ply(bytes.as_slice()).expect("degree-0 PLY");
    assert_eq!(g.sh_degree, 0);
    assert_eq!(&g.sh[0][..4], &[3.0, 4.0, 5.0, 0.0]);
    assert_eq!(g.rotations[0], [10.0, 11.0, 12.0, 13.0]);
}
