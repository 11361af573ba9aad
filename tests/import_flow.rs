//! The one-way flow of docs/architecture.md, checked on the source: a room of `src/` names
//! only rooms in lower layers (`crate::<room>` paths and `use` lines), never its own layer's
//! or a higher one's. Test code (files and folders named `tests`, `*_tests.rs`, and whatever
//! follows a file's first `#[cfg(test)]`) and comments are not counted.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

/// docs/architecture.md's layers, highest first.
const LAYERS: &[(u32, &[&str])] = &[
    (9, &["cli"]),
    (8, &["loadbench"]),
    (7, &["api", "worker", "gc"]),
    (6, &["webhooks"]),
    (5, &["config"]),
    (4, &["jobs", "store"]),
    (3, &["pipeline"]),
    (2, &["forest", "splat", "synth"]),
    (1, &["geom", "io", "gpu"]),
    (0, &["progress", "stage", "rng", "testing"]),
];

fn layer(room: &str) -> Option<u32> {
    LAYERS
        .iter()
        .find(|(_, rooms)| rooms.contains(&room))
        .map(|(l, _)| *l)
}

fn sources(dir: &Path, out: &mut Vec<PathBuf>) {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    for e in entries.flatten() {
        let p = e.path();
        let name = p.file_name().and_then(|n| n.to_str()).unwrap_or("");
        if p.is_dir() {
            if name != "tests" {
                sources(&p, out);
            }
        } else if name.ends_with(".rs") && name != "tests.rs" && !name.ends_with("_tests.rs") {
            out.push(p);
        }
    }
}

/// The rooms `text` names as `crate::<room>`, outside comments and test code.
fn named_rooms(text: &str) -> BTreeSet<String> {
    let mut rooms = BTreeSet::new();
    for line in text.lines() {
        let t = line.trim_start();
        if t.starts_with("#[cfg(test)]") {
            break;
        }
        if t.starts_with("//") {
            continue;
        }
        let mut rest = t;
        while let Some(i) = rest.find("crate::") {
            rest = &rest[i + "crate::".len()..];
            let room: String = rest
                .chars()
                .take_while(|c| c.is_ascii_lowercase() || *c == '_' || c.is_ascii_digit())
                .collect();
            if !room.is_empty() {
                rooms.insert(room);
            }
        }
    }
    rooms
}

#[test]
fn rooms_import_only_lower_layers() {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut files = Vec::new();
    sources(&src, &mut files);
    assert!(files.len() > 100, "found only {} source files", files.len());
    let mut wrong = Vec::new();
    for f in &files {
        let rel = f.strip_prefix(&src).expect("under src");
        let first = rel
            .components()
            .next()
            .and_then(|c| c.as_os_str().to_str())
            .unwrap_or("");
        let room = first.trim_end_matches(".rs");
        if matches!(room, "lib" | "main") {
            continue;
        }
        let Some(own) = layer(room) else {
            wrong.push(format!(
                "{}: room `{room}` is in no layer of docs/architecture.md",
                rel.display()
            ));
            continue;
        };
        let text = std::fs::read_to_string(f).expect("read source");
        for other in named_rooms(&text) {
            if other == room {
                continue;
            }
            match layer(&other) {
                Some(l) if l < own => {}
                Some(l) => wrong.push(format!(
                    "{}: `{room}` (layer {own}) uses `{other}` (layer {l})",
                    rel.display()
                )),
                None => wrong.push(format!(
                    "{}: `crate::{other}` is in no layer",
                    rel.display()
                )),
            }
        }
    }
    assert!(
        wrong.is_empty(),
        "imports against the one-way flow:\n{}",
        wrong.join("\n")
    );
}

#[test]
fn the_scanner_sees_uses_and_skips_comments_and_tests() {
    let text = "use crate::jobs::JobStore;\n// crate::api in a comment\nlet x = crate::io::read();\n#[cfg(test)]\nuse crate::cli;\n";
    let rooms: Vec<String> = named_rooms(text).into_iter().collect();
    assert_eq!(rooms, ["io", "jobs"]);
}
