//! Writes the seed corpora: `cargo run --release --bin seed -- CORPUS PLOT`, where PLOT is a
//! `sylva synth --preset tiny` folder (its CSVs and COLMAP model are cut down here). Each seed
//! is small and valid, made with Sylva's own writers, so the fuzzer starts inside every
//! format; `fuzz/corpus/` holds what this wrote.

use std::path::{Path, PathBuf};

use glam::{DVec3, Vec3};
use sylva::io::colmap;
use sylva::io::pointcloud::{CloudFormat, PointCloud};
use sylva::progress::NoProgress;
use sylva::pipeline::fuzz::join_parts;

fn put(corpus: &Path, target: &str, name: &str, bytes: &[u8]) {
    let dir = corpus.join(target);
    std::fs::create_dir_all(&dir).unwrap_or_else(|e| panic!("{}: {e}", dir.display()));
    std::fs::write(dir.join(name), bytes).unwrap_or_else(|e| panic!("{name}: {e}"));
}

fn cloud(n: usize, format: CloudFormat) -> PointCloud {
    PointCloud {
        offset: DVec3::new(500_000.0, 4_000_000.0, 100.0),
        positions: (0..n)
            .map(|i| Vec3::new(i as f32 * 0.1, (i % 3) as f32, (i % 5) as f32 * 0.5))
            .collect(),
        colors: Some((0..n).map(|i| [i as u8, 128, 255 - i as u8]).collect()),
        intensity: Some((0..n).map(|i| i as u16 * 100).collect()),
        format,
    }
}

fn read(path: &Path) -> Vec<u8> {
    std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

fn e57_seed(path: &Path) {
    use e57::{E57Writer, Record, RecordDataType, RecordName, RecordValue};
    let mut w = E57Writer::from_file(path, "sylva-fuzz-seed").expect("e57 writer");
    let double = || RecordDataType::Double {
        min: None,
        max: None,
    };
    let proto = vec![
        Record {
            name: RecordName::CartesianX,
            data_type: double(),
        },
        Record {
            name: RecordName::CartesianY,
            data_type: double(),
        },
        Record {
            name: RecordName::CartesianZ,
            data_type: double(),
        },
        Record {
            name: RecordName::Intensity,
            data_type: RecordDataType::Integer { min: 0, max: 255 },
        },
    ];
    let mut pc = w.add_pointcloud("scan", proto).expect("pointcloud");
    for i in 0..8 {
        pc.add_point(vec![
            RecordValue::Double(i as f64),
            RecordValue::Double(1.0),
            RecordValue::Double(2.0),
            RecordValue::Integer(i * 10),
        ])
        .expect("point");
    }
    pc.finalize().expect("finalize scan");
    w.finalize().expect("finalize file");
}

/// The plot's COLMAP model cut to two photos, their first keypoints and the points they see.
fn small_model(plot: &Path) -> colmap::ColmapModel {
    let project = colmap::find_project(&plot.join("colmap")).expect("colmap project");
    let full = colmap::read_model(&project.sparse_dir, &NoProgress).expect("model");
    let mut m = colmap::ColmapModel {
        cameras: full.cameras.clone(),
        ..Default::default()
    };
    let mut kept = std::collections::BTreeSet::new();
    for img in full.images.values().take(2) {
        let mut img = img.clone();
        img.points2d.truncate(6);
        for p in &img.points2d {
            if let Some(id) = p.point3d_id {
                kept.insert(id);
            }
        }
        m.images.insert(img.id, img);
    }
    for p in full.points.iter().filter(|p| kept.contains(&p.id)) {
        let mut p = p.clone();
        p.track.retain(|(img, idx)| {
            m.images
                .get(img)
                .is_some_and(|i| (*idx as usize) < i.points2d.len())
        });
        m.points.push(p);
    }
    m
}

fn zip_of(files: &[(&str, &[u8])]) -> Vec<u8> {
    use std::io::Write;
    let mut buf = std::io::Cursor::new(Vec::new());
    {
        let mut z = zip::ZipWriter::new(&mut buf);
        let opts = zip::write::SimpleFileOptions::default();
        for (name, bytes) in files {
            z.start_file(*name, opts).expect("zip entry");
            z.write_all(bytes).expect("zip write");
        }
        z.finish().expect("zip finish");
    }
    buf.into_inner()
}

/// A minimal JPEG: SOI, an APP1 "Exif" segment with `block`, EOI.
fn jpeg_with_exif(block: &[u8]) -> Vec<u8> {
    let mut out = vec![0xFF, 0xD8, 0xFF, 0xE1];
    let len = (2 + 6 + block.len()) as u16;
    out.extend_from_slice(&len.to_be_bytes());
    out.extend_from_slice(b"Exif\0\0");
    out.extend_from_slice(block);
    out.extend_from_slice(&[0xFF, 0xD9]);
    out
}

fn main() {
    let args: Vec<PathBuf> = std::env::args_os().skip(1).map(PathBuf::from).collect();
    let [corpus, plot] = args.as_slice() else {
        eprintln!("usage: seed CORPUS_DIR SYNTH_PLOT_DIR");
        std::process::exit(2);
    };
    let tmp = tempfile::tempdir().expect("tempdir");
    let t = tmp.path();

    // Point clouds.
    let las = t.join("a.las");
    sylva::io::las::write_las(&las, &cloud(12, CloudFormat::Las), false).expect("las");
    put(corpus, "las", "small.las", &read(&las));
    let laz = t.join("a.laz");
    sylva::io::las::write_las(&laz, &cloud(12, CloudFormat::Laz), true).expect("laz");
    put(corpus, "laz", "small.laz", &read(&laz));
    let ply = t.join("a.ply");
    sylva::io::ply::write_ply(&ply, &cloud(8, CloudFormat::Ply), &[]).expect("ply");
    put(corpus, "ply", "small.ply", &read(&ply));
    put(
        corpus,
        "ply",
        "ascii.ply",
        b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\nend_header\n0 0 0\n1 2 3\n",
    );
    let e57 = t.join("a.e57");
    e57_seed(&e57);
    put(corpus, "e57", "small.e57", &read(&e57));
    put(
        corpus,
        "xyz",
        "rgb.xyz",
        b"0 0 0 10 20 30\n1.5 2 3 40 50 60\n2 2 2 0 0 0\n",
    );
    put(
        corpus,
        "xyz",
        "comma.xyz",
        b"x,y,z,intensity\n1,2,3,100\n4,5,6,200\n",
    );

    // COLMAP models, binary and text: cameras, images and points3D joined.
    let model = small_model(plot);
    for (target, dir, ext) in [("colmap_bin", "bin", "bin"), ("colmap_text", "txt", "txt")] {
        let d = t.join(dir);
        std::fs::create_dir_all(&d).expect("dir");
        if ext == "bin" {
            colmap::write_binary(&model, &d).expect("write bin");
        } else {
            colmap::write_text(&model, &d).expect("write text");
        }
        let parts: Vec<Vec<u8>> = ["cameras", "images", "points3D"]
            .iter()
            .map(|f| read(&d.join(format!("{f}.{ext}"))))
            .collect();
        let refs: Vec<&[u8]> = parts.iter().map(Vec::as_slice).collect();
        put(corpus, target, "two_images", &join_parts(&refs));
    }

    // Archives: a zip of a small COLMAP project, and a tar.
    let d = t.join("txt");
    let cams = read(&d.join("cameras.txt"));
    let imgs = read(&d.join("images.txt"));
    let pts = read(&d.join("points3D.txt"));
    let project = zip_of(&[
        ("sparse/0/cameras.txt", &cams),
        ("sparse/0/images.txt", &imgs),
        ("sparse/0/points3D.txt", &pts),
        ("images/readme.txt", b"no photos in a seed"),
    ]);
    put(corpus, "archive", "project.zip", &project);
    let mut tar = tar::Builder::new(Vec::new());
    let mut h = tar::Header::new_gnu();
    h.set_size(5);
    h.set_mode(0o644);
    h.set_cksum();
    tar.append_data(&mut h, "dir/file.txt", &b"hello"[..])
        .expect("tar entry");
    put(
        corpus,
        "archive",
        "one.tar",
        &tar.into_inner().expect("tar"),
    );

    // Tables.
    let cp = read(&plot.join("control_points.csv"));
    put(corpus, "control_points", "plot.csv", &cp);
    let fd = read(&plot.join("field_dbh.csv"));
    put(corpus, "field_dbh", "plot.csv", &fd);

    // EXIF GPS.
    let fix = sylva::io::gps::GpsFix {
        lon: -92.1,
        lat: 46.8,
        alt: Some(310.5),
    };
    let block = sylva::io::gps::exif_block(&fix).expect("exif");
    put(corpus, "exif_gps", "fix.jpg", &jpeg_with_exif(&block));

    // A splat PLY of three Gaussians.
    let mut g = sylva::splat::model::Gaussians::default();
    for i in 0..3 {
        g.means.push([i as f32, 0.5, 1.0]);
        g.log_scales.push([-3.0, -2.5, -2.0]);
        g.rotations.push([1.0, 0.0, 0.0, 0.0]);
        g.opacity_logits.push(0.3);
        g.sh.push([0.1; sylva::splat::model::SH_FLOATS]);
        g.trunk_prob.push(0.2);
    }
    g.sh_degree = 1;
    let mut splat = Vec::new();
    sylva::splat::export::write_ply(&mut splat, &g).expect("splat ply");
    put(corpus, "splat_ply", "three.ply", &splat);

    // Job parameters.
    put(
        corpus,
        "params",
        "train.json",
        br#"{"until": "export", "train": {"steps": 30, "resolution": 64, "backend": "cpu"}, "export": {"tile_gaussians": 100}}"#,
    );
    put(corpus, "params", "empty.json", b"{}");

    // Uploads: the first byte picks the kind (0 cloud, 1 COLMAP, 2 photos, 3 control
    // points, 4 field DBH).
    let with_kind = |k: u8, body: &[u8]| [&[k][..], body].concat();
    put(corpus, "upload", "cloud", &with_kind(0, &read(&laz)));
    put(corpus, "upload", "colmap", &with_kind(1, &project));
    put(corpus, "upload", "control_points", &with_kind(3, &cp));
    put(corpus, "upload", "field_dbh", &with_kind(4, &fd));
    println!("seeds written to {}", corpus.display());
}
