//! Tests of safe archive extraction: hostile names, links, bombs and limits.

use std::io::Write;

use super::*;
use crate::progress::{Cancelled, NoProgress};
use zip::write::SimpleFileOptions;

/// Builds a zip of (name, contents) files; `symlink` adds a link entry.
fn zip_of(path: &Path, files: &[(&str, &[u8])], symlink: Option<&str>) {
    let mut z = zip::ZipWriter::new(File::create(path).unwrap());
    let opts = SimpleFileOptions::default().compression_method(zip::CompressionMethod::Deflated);
    for (name, data) in files {
        if name.ends_with('/') {
            z.add_directory(*name, opts).unwrap();
        } else {
            z.start_file(*name, opts).unwrap();
            z.write_all(data).unwrap();
        }
    }
    if let Some(link) = symlink {
        z.add_symlink(link, "/etc/passwd", opts).unwrap();
    }
    z.finish().unwrap();
}

/// Builds a tar with raw (unvalidated) names and entry types, optionally gzipped.
fn tar_of(path: &Path, entries: &[(&str, tar::EntryType, &[u8])], gz: bool) {
    let mut b = tar::Builder::new(Vec::new());
    for (name, ty, data) in entries {
        let mut h = tar::Header::new_ustar();
        h.as_old_mut().name[..name.len()].copy_from_slice(name.as_bytes());
        h.set_entry_type(*ty);
        h.set_size(data.len() as u64);
        h.set_mode(0o644);
        if *ty == tar::EntryType::Symlink || *ty == tar::EntryType::Link {
            h.as_old_mut().linkname[..6].copy_from_slice(b"target");
        }
        h.set_cksum();
        b.append(&h, *data).unwrap();
    }
    let bytes = b.into_inner().unwrap();
    let bytes = if gz {
        let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::default());
        e.write_all(&bytes).unwrap();
        e.finish().unwrap()
    } else {
        bytes
    };
    std::fs::write(path, bytes).unwrap();
}

fn extract(archive: &Path, dest: &Path) -> Result<ExtractSummary, ArchiveError> {
    extract_archive(archive, dest, &ExtractLimits::default(), &NoProgress)
}

#[test]
fn tar_gz_happy_path_extracts_files_and_folders() {
    let dir = tempfile::tempdir().unwrap();
    let (arc, dest) = (dir.path().join("upload.bin"), dir.path().join("out"));
    tar_of(
        &arc,
        &[
            ("project/", tar::EntryType::Directory, b""),
            (
                "project/sparse/cameras.txt",
                tar::EntryType::Regular,
                b"# cams\n",
            ),
            (
                "project/images/a.jpg",
                tar::EntryType::Regular,
                &[7u8; 3000],
            ),
            ("project/empty/", tar::EntryType::Directory, b""),
        ],
        true,
    );
    let s = extract(&arc, &dest).unwrap();
    assert_eq!(
        s,
        ExtractSummary {
            entries: 4,
            files: 2,
            unpacked_bytes: 3007
        }
    );
    assert_eq!(
        std::fs::read(dest.join("project/sparse/cameras.txt")).unwrap(),
        b"# cams\n"
    );
    assert!(dest.join("project/empty").is_dir());
    // The destination must be fresh.
    assert!(matches!(
        extract(&arc, &dest),
        Err(ArchiveError::File(IoError::Io { .. }))
    ));
}

#[test]
fn zip_and_plain_tar_extract() {
    let dir = tempfile::tempdir().unwrap();
    let zip = dir.path().join("a.zip");
    zip_of(
        &zip,
        &[("d/", b""), ("d/x.txt", b"hello"), ("./y.txt", b"yo")],
        None,
    );
    let s = extract(&zip, &dir.path().join("z")).unwrap();
    assert_eq!((s.files, s.unpacked_bytes), (2, 7));
    assert_eq!(
        std::fs::read(dir.path().join("z/d/x.txt")).unwrap(),
        b"hello"
    );
    let tar = dir.path().join("a.tar");
    tar_of(&tar, &[("f.txt", tar::EntryType::Regular, b"abc")], false);
    assert_eq!(extract(&tar, &dir.path().join("t")).unwrap().files, 1);
}

#[test]
fn hostile_names_are_refused_and_nothing_is_left() {
    let dir = tempfile::tempdir().unwrap();
    let cases: [&str; 5] = [
        "../evil",
        "ok/../../evil",
        "/abs/evil",
        "C:/evil",
        "..\\evil",
    ];
    for (k, name) in cases.iter().enumerate() {
        let zip = dir.path().join(format!("{k}.zip"));
        zip_of(&zip, &[("fine.txt", b"x"), (name, b"evil")], None);
        let dest = dir.path().join(format!("zip{k}"));
        let e = extract(&zip, &dest);
        assert!(
            matches!(e, Err(ArchiveError::UnsafePath { .. })),
            "zip {name}: {e:?}"
        );
        assert!(!dest.exists(), "zip {name}: leftovers");
        let tar = dir.path().join(format!("{k}.tar"));
        tar_of(
            &tar,
            &[
                ("fine.txt", tar::EntryType::Regular, b"x"),
                (name, tar::EntryType::Regular, b"e"),
            ],
            false,
        );
        let e = extract(&tar, &dir.path().join(format!("tar{k}")));
        assert!(
            matches!(e, Err(ArchiveError::UnsafePath { .. })),
            "tar {name}: {e:?}"
        );
    }
    assert!(!dir.path().join("evil").exists());
}

#[test]
fn links_and_special_files_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let zip = dir.path().join("l.zip");
    zip_of(&zip, &[("a.txt", b"x")], Some("link"));
    assert!(matches!(
        extract(&zip, &dir.path().join("z")),
        Err(ArchiveError::Link { .. })
    ));
    for (k, ty) in [tar::EntryType::Symlink, tar::EntryType::Link]
        .into_iter()
        .enumerate()
    {
        let tar = dir.path().join(format!("l{k}.tar"));
        tar_of(
            &tar,
            &[("a.txt", tar::EntryType::Regular, b"x"), ("link", ty, b"")],
            k == 1,
        );
        let e = extract(&tar, &dir.path().join(format!("t{k}")));
        assert!(matches!(e, Err(ArchiveError::Link { .. })), "{e:?}");
    }
    let tar = dir.path().join("fifo.tar");
    tar_of(
        &tar,
        &[
            ("a.txt", tar::EntryType::Regular, b"x"),
            ("p", tar::EntryType::Fifo, b""),
        ],
        false,
    );
    let e = extract(&tar, &dir.path().join("f"));
    assert!(matches!(e, Err(ArchiveError::SpecialFile { .. })), "{e:?}");
}

#[test]
fn zip_bomb_trips_the_ratio_and_size_limits() {
    let dir = tempfile::tempdir().unwrap();
    let zip = dir.path().join("bomb.zip");
    zip_of(&zip, &[("zeros.bin", &vec![0u8; 50 << 20])], None);
    assert!(std::fs::metadata(&zip).unwrap().len() < 1 << 20);
    let dest = dir.path().join("b");
    let e = extract(&zip, &dest);
    assert!(
        matches!(e, Err(ArchiveError::RatioExceeded { .. })),
        "{e:?}"
    );
    assert!(!dest.exists());

    let small = dir.path().join("small.zip");
    zip_of(&small, &[("a.bin", &[1u8; 5000])], None);
    let limits = ExtractLimits {
        max_unpacked_bytes: 1000,
        ..Default::default()
    };
    let e = extract_archive(&small, &dest, &limits, &NoProgress);
    assert!(
        matches!(e, Err(ArchiveError::TooLarge { limit: 1000 })),
        "{e:?}"
    );
}

#[test]
fn too_many_entries_empty_and_unknown_archives_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let limits = ExtractLimits {
        max_entries: 3,
        ..Default::default()
    };
    let files: Vec<(String, &[u8])> = (0..5).map(|i| (format!("f{i}"), &b"x"[..])).collect();
    let refs: Vec<(&str, &[u8])> = files.iter().map(|(n, d)| (n.as_str(), *d)).collect();
    let zip = dir.path().join("many.zip");
    zip_of(&zip, &refs, None);
    let e = extract_archive(&zip, &dir.path().join("m"), &limits, &NoProgress);
    assert!(
        matches!(e, Err(ArchiveError::TooManyEntries { limit: 3 })),
        "{e:?}"
    );
    let tar = dir.path().join("many.tar");
    let entries: Vec<_> = refs
        .iter()
        .map(|(n, d)| (*n, tar::EntryType::Regular, *d))
        .collect();
    tar_of(&tar, &entries, false);
    let e = extract_archive(&tar, &dir.path().join("mt"), &limits, &NoProgress);
    assert!(
        matches!(e, Err(ArchiveError::TooManyEntries { .. })),
        "{e:?}"
    );

    let empty = dir.path().join("empty.zip");
    zip_of(&empty, &[], None);
    assert!(matches!(
        extract(&empty, &dir.path().join("e")),
        Err(ArchiveError::Empty)
    ));
    let dirs_only = dir.path().join("dirs.tar.gz");
    tar_of(&dirs_only, &[("d/", tar::EntryType::Directory, b"")], true);
    assert!(matches!(
        extract(&dirs_only, &dir.path().join("e2")),
        Err(ArchiveError::Empty)
    ));
    assert!(!dir.path().join("e2").exists());

    let junk = dir.path().join("junk.zip");
    std::fs::write(&junk, b"this is not an archive").unwrap();
    assert!(matches!(
        extract(&junk, &dir.path().join("j")),
        Err(ArchiveError::UnknownFormat)
    ));
}

#[test]
fn cancellation_stops_and_cleans_up() {
    let dir = tempfile::tempdir().unwrap();
    let zip = dir.path().join("a.zip");
    zip_of(&zip, &[("a.txt", b"x")], None);
    let dest = dir.path().join("c");
    std::fs::create_dir(&dest).unwrap();
    let e = extract_archive(&zip, &dest, &ExtractLimits::default(), &Cancelled);
    assert!(matches!(e, Err(ArchiveError::File(IoError::Cancelled))));
    assert!(dest.is_dir() && std::fs::read_dir(&dest).unwrap().next().is_none());
}
