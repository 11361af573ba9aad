//! A folder of photos, as a job gives them to stage `sfm` (an unpacked `photos` upload, or
//! `sylva run --photos DIR`): where the photos lie in it, their names as COLMAP will call
//! them, and a check that each is a photo Sylva and COLMAP can read.
//!
//! A photo is a file ending in `.jpg`, `.jpeg`, `.png`, `.tif` or `.tiff` (any case), found
//! anywhere under the folder; its name is its path relative to the folder with `/`
//! separators, which is also the name COLMAP's feature extractor gives it when run with the
//! folder as `--image_path`. Hidden files and macOS's `__MACOSX` folders are skipped.

use std::path::{Path, PathBuf};

use rayon::prelude::*;
use serde::Serialize;

use super::IoError;

/// File name endings taken as photos (lower case; the check ignores case).
pub const PHOTO_EXTENSIONS: [&str; 5] = ["jpg", "jpeg", "png", "tif", "tiff"];

/// Whether `name` ends like a photo.
pub fn is_photo_name(name: &str) -> bool {
    name.rsplit_once('.')
        .is_some_and(|(_, ext)| PHOTO_EXTENSIONS.iter().any(|e| ext.eq_ignore_ascii_case(e)))
}

fn skipped(name: &str) -> bool {
    name.starts_with('.') || name == "__MACOSX"
}

/// The folder under `root` that holds the photos: `root` itself, or, when `root` holds no
/// photo but exactly one folder (archives often wrap everything in one) or an `images/`
/// folder, that folder, two levels at most.
pub fn find_photos_dir(root: &Path) -> Result<PathBuf, IoError> {
    let mut base = root.to_path_buf();
    for _ in 0..3 {
        let mut dirs = Vec::new();
        let mut photos = 0usize;
        for entry in std::fs::read_dir(&base).map_err(|e| IoError::io(&base, e))? {
            let entry = entry.map_err(|e| IoError::io(&base, e))?;
            let name = entry.file_name().to_string_lossy().into_owned();
            if skipped(&name) {
                continue;
            }
            let path = entry.path();
            if path.is_dir() {
                dirs.push(path);
            } else if is_photo_name(&name) {
                photos += 1;
            }
        }
        if photos > 0 {
            return Ok(base);
        }
        let images = base.join("images");
        base = match dirs.as_slice() {
            [only] => only.clone(),
            _ if images.is_dir() => images,
            _ => break,
        };
    }
    // Photos only deeper down (one folder per flight, say): the root, searched recursively.
    if list_photos(root)?.is_empty() {
        Err(IoError::format(
            root,
            format!(
                "no photos found (files ending in {})",
                PHOTO_EXTENSIONS.map(|e| format!(".{e}")).join(", ")
            ),
        ))
    } else {
        Ok(root.to_path_buf())
    }
}

/// Every photo under `dir`, recursively, by its name relative to `dir` (`/` separators),
/// sorted.
pub fn list_photos(dir: &Path) -> Result<Vec<String>, IoError> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for entry in std::fs::read_dir(&d).map_err(|e| IoError::io(&d, e))? {
            let entry = entry.map_err(|e| IoError::io(&d, e))?;
            let name = entry.file_name().to_string_lossy().into_owned();
            if skipped(&name) {
                continue;
            }
            let path = entry.path();
            if path.is_dir() {
                stack.push(path);
            } else if is_photo_name(&name) {
                out.push(super::relative_name(&path, dir));
            }
        }
    }
    out.sort();
    Ok(out)
}

/// The fewest photos structure from motion can use.
pub const MIN_PHOTOS: usize = 3;

/// A folder of photos checked for stage `sfm`: where they lie, their names and sizes.
#[derive(Debug, Clone)]
pub struct PhotoSet {
    pub dir: PathBuf,
    pub names: Vec<String>,
    pub check: PhotoCheck,
}

/// Finds the photos under `root` ([`find_photos_dir`]), lists them and reads each header;
/// a `Format` error when there are fewer than [`MIN_PHOTOS`] or any cannot be read (naming
/// the first five). The one check an upload's inspection, stage `ingest` and stage `sfm`
/// share.
pub fn usable_photos(root: &Path) -> Result<PhotoSet, IoError> {
    let dir = find_photos_dir(root)?;
    let names = list_photos(&dir)?;
    if names.len() < MIN_PHOTOS {
        return Err(IoError::format(
            root,
            format!(
                "{} photo(s) found; structure from motion needs at least {MIN_PHOTOS} \
                 overlapping photos",
                names.len()
            ),
        ));
    }
    let check = check_photos(&dir, &names);
    if !check.unreadable.is_empty() {
        let shown: Vec<String> = check
            .unreadable
            .iter()
            .take(5)
            .map(|f| format!("{} ({})", f.name, f.fault))
            .collect();
        return Err(IoError::format(
            root,
            format!(
                "{} photo(s) cannot be read: {}{}",
                check.unreadable.len(),
                shown.join(", "),
                if check.unreadable.len() > 5 {
                    ", …"
                } else {
                    ""
                }
            ),
        ));
    }
    Ok(PhotoSet { dir, names, check })
}

/// Each distinct size of a checked set as the reports give it: width, height, photos.
pub fn sizes_json(check: &PhotoCheck) -> serde_json::Value {
    check
        .size_counts()
        .iter()
        .map(|(s, n)| serde_json::json!({ "width": s[0], "height": s[1], "photos": n }))
        .collect()
}

/// One photo that cannot be read, with why.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PhotoFault {
    pub name: String,
    pub fault: String,
}

/// What [`check_photos`] found.
#[derive(Debug, Clone, Serialize)]
pub struct PhotoCheck {
    /// Readable photos, by name, with their size (pixels, width × height).
    pub sizes: Vec<(String, [u32; 2])>,
    /// Photos whose header cannot be read.
    pub unreadable: Vec<PhotoFault>,
}

impl PhotoCheck {
    /// Each distinct size (width, height) with how many photos have it, most common first.
    pub fn size_counts(&self) -> Vec<([u32; 2], usize)> {
        let mut counts: Vec<([u32; 2], usize)> = Vec::new();
        for (_, s) in &self.sizes {
            match counts.iter_mut().find(|(c, _)| c == s) {
                Some((_, n)) => *n += 1,
                None => counts.push((*s, 1)),
            }
        }
        counts.sort_by(|a, b| b.1.cmp(&a.1).then(a.0.cmp(&b.0)));
        counts
    }
}

/// Reads the header of every photo in `names` (under `dir`), in parallel: its size, or why
/// it cannot be read (not an image, truncated header, a format the `image` crate does not
/// read).
pub fn check_photos(dir: &Path, names: &[String]) -> PhotoCheck {
    let read: Vec<(String, Result<[u32; 2], String>)> = names
        .par_iter()
        .map(|name| {
            let path = dir.join(name);
            let size = image::ImageReader::open(&path)
                .map_err(|e| e.to_string())
                .and_then(|r| r.with_guessed_format().map_err(|e| e.to_string()))
                .and_then(|r| r.into_dimensions().map_err(|e| e.to_string()))
                .map(|(w, h)| [w, h]);
            (name.clone(), size)
        })
        .collect();
    let mut check = PhotoCheck {
        sizes: Vec::new(),
        unreadable: Vec::new(),
    };
    for (name, r) in read {
        match r {
            Ok(s) => check.sizes.push((name, s)),
            Err(fault) => check.unreadable.push(PhotoFault { name, fault }),
        }
    }
    check
}

#[cfg(test)]
mod tests {
    use super::*;

    fn png(path: &Path, w: u32, h: u32) {
        let img = image::RgbImage::from_pixel(w, h, image::Rgb([90, 120, 60]));
        img.save(path).expect("write png");
    }

    #[test]
    fn photos_are_found_inside_a_wrapping_folder_and_named_as_colmap_names_them() {
        let dir = tempfile::tempdir().expect("tmp");
        let root = dir.path().join("upload");
        let inner = root.join("flight").join("images");
        std::fs::create_dir_all(inner.join("north")).expect("mkdir");
        std::fs::create_dir_all(root.join("__MACOSX")).expect("mkdir");
        png(&inner.join("a.PNG"), 8, 6);
        png(&inner.join("north").join("b.png"), 8, 6);
        std::fs::write(inner.join("notes.txt"), b"x").expect("write");
        std::fs::write(inner.join(".hidden.jpg"), b"x").expect("write");
        let found = find_photos_dir(&root).expect("found");
        assert_eq!(found, inner);
        let names = list_photos(&found).expect("list");
        assert_eq!(names, vec!["a.PNG".to_string(), "north/b.png".to_string()]);
        let check = check_photos(&found, &names);
        assert!(check.unreadable.is_empty());
        assert_eq!(check.size_counts(), vec![([8, 6], 2)]);
    }

    #[test]
    fn a_folder_without_photos_and_a_broken_photo_are_named() {
        let dir = tempfile::tempdir().expect("tmp");
        std::fs::write(dir.path().join("readme.md"), b"x").expect("write");
        let e = find_photos_dir(dir.path()).expect_err("no photos");
        assert!(e.to_string().contains("no photos found"), "{e}");
        std::fs::write(dir.path().join("bad.jpg"), b"not a jpeg at all").expect("write");
        png(&dir.path().join("good.png"), 4, 4);
        let names = list_photos(dir.path()).expect("list");
        let check = check_photos(dir.path(), &names);
        assert_eq!(check.unreadable.len(), 1);
        assert_eq!(check.unreadable[0].name, "bad.jpg");
        assert_eq!(check.sizes.len(), 1);
        let e = usable_photos(dir.path()).expect_err("two photos, one broken");
        assert!(e.to_string().contains("2 photo(s) found"), "{e}");
        png(&dir.path().join("third.png"), 4, 4);
        let e = usable_photos(dir.path()).expect_err("one broken");
        assert!(
            e.to_string().contains("1 photo(s) cannot be read: bad.jpg"),
            "{e}"
        );
        std::fs::remove_file(dir.path().join("bad.jpg")).expect("rm");
        png(&dir.path().join("fourth.png"), 4, 4);
        let set = usable_photos(dir.path()).expect("usable");
        assert_eq!(set.names, ["fourth.png", "good.png", "third.png"]);
        assert_eq!(
            sizes_json(&set.check),
            serde_json::json!([{"width": 4, "height": 4, "photos": 3}])
        );
    }
}
