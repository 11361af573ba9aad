//! The fuzz targets: every reader of a file a stranger can send, each behind one name, fed the
//! bytes of one input. The coverage-guided fuzzer (`fuzz/`, afl.rs) and the corpus replay
//! test (`tests/fuzz_corpora.rs`) both call [`run`], so what the fuzzer found is replayed by
//! the README's test command.
//!
//! A reader may refuse an input (`Err`); a panic, a hang or an allocation beyond what the
//! input can hold is a finding. Inputs go through the same file-based entry points as uploads
//! do, written first to a scratch folder.

use std::path::Path;

use crate::io::archive::ExtractLimits;
use crate::progress::NoProgress;

/// The targets, by name (also the corpus folders under `fuzz/corpus/`).
pub const TARGETS: &[&str] = &[
    "las",
    "laz",
    "ply",
    "e57",
    "xyz",
    "colmap_bin",
    "colmap_text",
    "archive",
    "control_points",
    "field_dbh",
    "exif_gps",
    "splat_ply",
    "params",
    "upload",
];

/// Limits of the archive target: small, so that a finding is about the reader and not the
/// disk (the service's defaults allow 200 GiB).
pub const FUZZ_EXTRACT_LIMITS: ExtractLimits = ExtractLimits {
    max_entries: 1_000,
    max_unpacked_bytes: 64 << 20,
    max_ratio: 200.0,
};

/// Splits `data` into `n` parts: each but the last is prefixed by its length (u32, little
/// endian, cut to what remains), so the fuzzer can grow and shrink each file of a set.
pub fn split_parts(data: &[u8], n: usize) -> Vec<&[u8]> {
    let mut out = Vec::with_capacity(n);
    let mut rest = data;
    for _ in 0..n.saturating_sub(1) {
        let (len, tail) = match rest.split_first_chunk::<4>() {
            Some((h, t)) => (u32::from_le_bytes(*h) as usize, t),
            None => (0, &[][..]),
        };
        let len = len.min(tail.len());
        out.push(&tail[..len]);
        rest = &tail[len..];
    }
    out.push(rest);
    out
}

/// Joins files into one input of [`split_parts`] (for seeding corpora).
pub fn join_parts(parts: &[&[u8]]) -> Vec<u8> {
    let mut out = Vec::new();
    for (i, p) in parts.iter().enumerate() {
        if i + 1 < parts.len() {
            out.extend_from_slice(&(p.len() as u32).to_le_bytes());
        }
        out.extend_from_slice(p);
    }
    out
}

fn write(dir: &Path, name: &str, data: &[u8]) -> Result<std::path::PathBuf, String> {
    let path = dir.join(name);
    std::fs::write(&path, data).map_err(|e| format!("scratch {}: {e}", path.display()))?;
    Ok(path)
}

/// A fresh, empty folder `name` under `scratch`.
fn fresh(scratch: &Path, name: &str) -> Result<std::path::PathBuf, String> {
    let d = scratch.join(name);
    if d.exists() {
        std::fs::remove_dir_all(&d).map_err(|e| format!("{}: {e}", d.display()))?;
    }
    std::fs::create_dir_all(&d).map_err(|e| format!("{}: {e}", d.display()))?;
    Ok(d)
}

/// Runs target `name` on `data`, using `scratch` (an existing folder) for its files. `Ok` when
/// the reader accepted the input, `Err` with its message when it refused it; an unknown target
/// is an `Err` too. Panics only where the reader does (a finding).
pub fn run(name: &str, data: &[u8], scratch: &Path) -> Result<(), String> {
    use crate::io::{colmap, gps, pointcloud, tables};
    let e = |e: &dyn std::fmt::Display| e.to_string();
    match name {
        "las" | "laz" | "ply" | "e57" | "xyz" => {
            let path = write(scratch, &format!("input.{name}"), data)?;
            let summary = pointcloud::inspect_point_cloud(&path).map_err(|x| e(&x));
            let cloud = pointcloud::read_point_cloud(&path, &NoProgress).map_err(|x| e(&x))?;
            summary.map(|_| ())?;
            let _ = cloud.len();
            Ok(())
        }
        "colmap_bin" | "colmap_text" => {
            let dir = fresh(scratch, "sparse")?;
            let ext = if name == "colmap_bin" { "bin" } else { "txt" };
            let parts = split_parts(data, 3);
            for (file, bytes) in ["cameras", "images", "points3D"].iter().zip(&parts) {
                write(&dir, &format!("{file}.{ext}"), bytes)?;
            }
            colmap::read_model(&dir, &NoProgress)
                .map(|_| ())
                .map_err(|x| e(&x))
        }
        "archive" => {
            let path = write(scratch, "input.archive", data)?;
            let dest = scratch.join("unpacked");
            if dest.exists() {
                std::fs::remove_dir_all(&dest).map_err(|x| e(&x))?;
            }
            crate::io::archive::extract_archive(&path, &dest, &FUZZ_EXTRACT_LIMITS, &NoProgress)
                .map(|_| ())
                .map_err(|x| e(&x))
        }
        "control_points" => {
            let path = write(scratch, "control_points.csv", data)?;
            tables::read_control_points(&path)
                .map(|_| ())
                .map_err(|x| e(&x))
        }
        "field_dbh" => {
            let path = write(scratch, "field_dbh.csv", data)?;
            tables::read_field_dbh(&path).map(|_| ()).map_err(|x| e(&x))
        }
        "exif_gps" => {
            let path = write(scratch, "photo.jpg", data)?;
            gps::read_fix(&path).map(|_| ())
        }
        "splat_ply" => crate::splat::export::read_ply(data)
            .map(|_| ())
            .map_err(|x| e(&x)),
        "params" => {
            let p: crate::pipeline::params::PipelineParams =
                serde_json::from_slice(data).map_err(|x| e(&x))?;
            let _ = p.train.config();
            let _ = p.stages();
            Ok(())
        }
        "upload" => {
            use crate::stage::UploadKind;
            let (kind, body) = match data.split_first() {
                Some((k, rest)) => (k % 5, rest),
                None => (0, data),
            };
            let (kind, file) = match kind {
                0 => (UploadKind::Lidar, "cloud.laz"),
                1 => (UploadKind::Colmap, "project.zip"),
                2 => (UploadKind::Photos, "photos.zip"),
                3 => (UploadKind::ControlPoints, "control_points.csv"),
                _ => (UploadKind::FieldDbh, "field_dbh.csv"),
            };
            let blob = write(scratch, "upload.blob", body)?;
            let unpack = scratch.join("upload-unpacked");
            if unpack.exists() {
                std::fs::remove_dir_all(&unpack).map_err(|x| e(&x))?;
            }
            crate::pipeline::inspect::inspect_upload(
                kind,
                file,
                &blob,
                &unpack,
                &FUZZ_EXTRACT_LIMITS,
                &NoProgress,
            )
            .map(|_| ())
            .map_err(|x| e(&x))
        }
        other => Err(format!(
            "no fuzz target {other:?} (targets: {})",
            TARGETS.join(", ")
        )),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parts_split_and_join_back() {
        let files: [&[u8]; 3] = [b"abc", b"", b"defgh"];
        let joined = join_parts(&files);
        assert_eq!(split_parts(&joined, 3), files.to_vec());
        // Lengths past the end are cut; missing parts are empty.
        assert_eq!(
            split_parts(&[9, 0, 0, 0, 1, 2], 3),
            vec![&[1u8, 2][..], &[][..], &[][..]]
        );
        let empty: &[u8] = &[];
        assert_eq!(split_parts(empty, 2), vec![empty, empty]);
    }

    #[test]
    fn an_unknown_target_is_an_error() {
        let dir = tempfile::tempdir().expect("tempdir");
        let err = run("nope", b"", dir.path()).expect_err("unknown");
        assert!(err.contains("las"), "{err}");
    }
}
