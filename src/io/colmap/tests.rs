//! Tests of the COLMAP readers, writers, project discovery and photo check.

use super::*;
use crate::progress::NoProgress;

fn model() -> ColmapModel {
    let mut m = ColmapModel::default();
    m.cameras.insert(
        1,
        Camera {
            id: 1,
            model: CameraModel::Pinhole,
            width: 8,
            height: 6,
            params: vec![4.5, 4.25, 4.0, 3.0],
        },
    );
    m.cameras.insert(
        7,
        Camera {
            id: 7,
            model: CameraModel::Opencv,
            width: 4000,
            height: 3000,
            params: vec![3000.1, 3000.2, 2000.0, 1500.0, -0.1, 0.01, 1e-4, -2e-5],
        },
    );
    m.images.insert(
        3,
        Image {
            id: 3,
            qvec: [0.6, 0.0, 0.8, 0.0],
            tvec: [1.25, -3.5, 10.0],
            camera_id: 1,
            name: "a.png".into(),
            points2d: vec![
                Point2D {
                    xy: [1.5, 2.25],
                    point3d_id: Some(0),
                },
                Point2D {
                    xy: [7.0, 0.5],
                    point3d_id: None,
                },
            ],
        },
    );
    m.images.insert(
        4,
        Image {
            id: 4,
            qvec: [1.0, 0.0, 0.0, 0.0],
            tvec: [0.0, 0.0, 0.1],
            camera_id: 7,
            name: "sub dir/b.png".into(),
            points2d: vec![],
        },
    );
    m.points.push(Point3D {
        id: 0,
        xyz: DVec3::new(0.1, -2.0, 33.333333333333336),
        rgb: [10, 200, 255],
        error: 0.75,
        track: vec![(3, 0)],
    });
    m.points.push(Point3D {
        id: 9,
        xyz: DVec3::ZERO,
        rgb: [0, 0, 0],
        error: 0.0,
        track: vec![],
    });
    m
}

#[test]
fn camera_model_table_matches_colmap() {
    assert_eq!(CameraModel::from_id(1), Some(CameraModel::Pinhole));
    assert_eq!(
        CameraModel::from_name("THIN_PRISM_FISHEYE").map(|m| m.model_id()),
        Some(10)
    );
    let counts: Vec<usize> = (0..=10)
        .filter_map(CameraModel::from_id)
        .map(|m| m.num_params())
        .collect();
    assert_eq!(counts, [3, 4, 4, 5, 8, 8, 12, 5, 4, 5, 12]);
    assert!(CameraModel::Opencv.is_supported() && !CameraModel::Fov.is_supported());
    assert_eq!(CameraModel::from_id(11), None);
    assert_eq!(CameraModel::from_id(-1), None);
}

#[test]
fn unsupported_cameras_are_named_with_the_models_sylva_can_use() {
    let mut m = model();
    assert_eq!(m.check_cameras(), Ok(()));
    let template = m.cameras[&7].clone();
    for id in 20..27 {
        let model = if id == 20 {
            CameraModel::OpencvFisheye
        } else {
            CameraModel::Fov
        };
        m.cameras.insert(
            id,
            Camera {
                id,
                model,
                ..template.clone()
            },
        );
    }
    let e = m.check_cameras().expect_err("fisheye and FOV cameras");
    assert!(
        e.starts_with(
            "unsupported camera model (camera 20 uses OPENCV_FISHEYE, camera 21 uses FOV"
        ),
        "{e}"
    );
    assert!(e.contains("and 2 more)"), "{e}");
    assert!(
        e.ends_with("supported: SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV"),
        "{e}"
    );
    let project = ColmapProject {
        sparse_dir: PathBuf::new(),
        images_dir: None,
        binary: true,
    };
    let s = summary(&project, &m);
    assert_eq!(s["format"], "binary");
    assert_eq!(s["cameras"], 9);
    assert_eq!(
        s["camera_models"],
        serde_json::json!(["FOV", "OPENCV", "OPENCV_FISHEYE", "PINHOLE"])
    );
}

#[test]
fn text_and_binary_round_trips_are_exact() {
    let dir = tempfile::tempdir().unwrap();
    let m = model();
    let (txt, bin, back) = (
        dir.path().join("t"),
        dir.path().join("b"),
        dir.path().join("tb"),
    );
    write_text(&m, &txt).unwrap();
    write_binary(&m, &bin).unwrap();
    let from_txt = read_model(&txt, &NoProgress).unwrap();
    let from_bin = read_model(&bin, &NoProgress).unwrap();
    assert_eq!(from_txt, m);
    assert_eq!(from_bin, m);
    // text -> binary -> text
    write_binary(&from_txt, &back).unwrap();
    write_text(&read_model(&back, &NoProgress).unwrap(), &txt).unwrap();
    assert_eq!(read_model(&txt, &NoProgress).unwrap(), m);
}

fn expect_format(dir: &Path, needle: &str) {
    match read_model(dir, &NoProgress) {
        Err(IoError::Format { path, fault }) => {
            let msg = format!("{}: {fault}", path.display());
            assert!(msg.contains(needle), "{msg} lacks {needle}");
        }
        other => panic!("expected a Format error with {needle}, got {other:?}"),
    }
}

#[test]
fn broken_text_models_are_rejected_with_line_numbers() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    write_text(&model(), d).unwrap();
    let cams = d.join("cameras.txt");
    let good = std::fs::read_to_string(&cams).unwrap();
    std::fs::write(&cams, good.replace("PINHOLE", "PINHOLEX")).unwrap();
    expect_format(d, "line 4: unknown camera model");
    std::fs::write(&cams, good.replace(" 4.5 ", " ")).unwrap();
    expect_format(d, "PINHOLE takes 4 parameters, found 3");
    std::fs::write(&cams, &good).unwrap();
    let imgs = d.join("images.txt");
    let good_imgs = std::fs::read_to_string(&imgs).unwrap();
    std::fs::write(&imgs, good_imgs.replace(" 7 sub dir", " 8 sub dir")).unwrap();
    expect_format(d, "image 4 references missing camera 8");
    std::fs::write(&imgs, good_imgs.replace("2.25 0", "2.25")).unwrap();
    expect_format(d, "images.txt: line 6");
    std::fs::write(&imgs, &good_imgs).unwrap();
    let mut bad = model();
    if let Some(c) = bad.cameras.get_mut(&1) {
        c.params.pop();
    }
    assert!(matches!(
        write_binary(&bad, &d.join("x")),
        Err(IoError::Format { .. })
    ));
    std::fs::remove_file(d.join("points3D.txt")).unwrap();
    expect_format(d, "points3D.txt: required COLMAP file is missing");
}

#[test]
fn broken_binary_models_are_rejected() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    write_binary(&model(), d).unwrap();
    let pts = d.join("points3D.bin");
    let bytes = std::fs::read(&pts).unwrap();
    std::fs::write(&pts, &bytes[..bytes.len() - 3]).unwrap();
    expect_format(d, "point3D record 1: file is truncated");
    // A huge declared count must fail on truncation, not on allocation.
    let mut huge = bytes.clone();
    huge[..8].copy_from_slice(&u64::MAX.to_le_bytes());
    std::fs::write(&pts, &huge).unwrap();
    expect_format(d, "file is truncated");
    std::fs::write(&pts, &bytes).unwrap();
    let cams = d.join("cameras.bin");
    let mut c = std::fs::read(&cams).unwrap();
    c[12..16].copy_from_slice(&42i32.to_le_bytes()); // model id of the first camera
    std::fs::write(&cams, &c).unwrap();
    expect_format(d, "camera record 0: unknown camera model id 42");
}

#[test]
fn find_project_handles_layouts() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().join("upload");
    let wrapped = root.join("my_project");
    write_binary(&model(), &wrapped.join("sparse/0")).unwrap();
    std::fs::create_dir_all(wrapped.join("images")).unwrap();
    std::fs::create_dir_all(root.join("__MACOSX")).unwrap();
    let p = find_project(&root).unwrap();
    assert_eq!(p.sparse_dir, wrapped.join("sparse/0"));
    assert_eq!(p.images_dir, Some(wrapped.join("images")));
    assert!(p.binary);

    let flat = dir.path().join("flat");
    write_text(&model(), &flat).unwrap();
    let p = find_project(&flat).unwrap();
    assert_eq!(
        (p.sparse_dir.as_path(), p.images_dir.clone(), p.binary),
        (flat.as_path(), None, false)
    );

    let empty = dir.path().join("empty");
    std::fs::create_dir_all(empty.join("a")).unwrap();
    std::fs::create_dir_all(empty.join("b")).unwrap();
    assert!(matches!(find_project(&empty), Err(IoError::Format { .. })));
}

#[test]
fn validate_images_reports_missing_broken_and_mis_sized_photos() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    let mut m = model();
    write_text(&m, &root.join("sparse")).unwrap();
    let images = root.join("images");
    std::fs::create_dir_all(images.join("sub dir")).unwrap();
    image::RgbImage::new(8, 6)
        .save(images.join("a.png"))
        .unwrap();
    let p = find_project(root).unwrap();
    let check = validate_images(&p, &m, &NoProgress).unwrap();
    assert_eq!((check.images_registered, check.images_found), (2, 1));
    assert_eq!(check.missing, vec!["sub dir/b.png".to_string()]);

    std::fs::write(images.join("sub dir/b.png"), b"not a png").unwrap();
    image::RgbImage::new(9, 6)
        .save(images.join("a.png"))
        .unwrap();
    let check = validate_images(&p, &m, &NoProgress).unwrap();
    assert_eq!(check.images_found, 2);
    assert_eq!(check.undecodable.len(), 1);
    assert_eq!(check.size_mismatch[0].found, [9, 6]);
    assert!(
        serde_json::to_string(&check)
            .unwrap()
            .contains("size_mismatch")
    );

    if let Some(img) = m.images.get_mut(&4) {
        img.name = "../escape.png".into();
    }
    assert!(matches!(
        validate_images(&p, &m, &NoProgress),
        Err(IoError::Format { .. })
    ));
}
