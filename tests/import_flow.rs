//! The one-way flow of docs/architecture.md, checked on the source: a room of `src/` names
//! only rooms in lower layers, never its own layer's or a higher one's. Test code (files and
//! folders named `tests`, `*_tests.rs`, and whatever follows a file's first `#[cfg(test)]`) and
//! comments are not counted.
//!
//! `src/` holds two crates. The library (`src/lib.rs`) has most rooms and names them as
//! `crate::<room>`; the binary (`src/main.rs`) has the command line and the benchmarks
//! (`cli`, `loadbench`), names its own rooms as `crate::<room>` and the library's as
//! `sylva::<room>`. Both spellings count, and each crate root must declare exactly its rooms.

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
    (3, &["pipeline", "nerf"]),
    (2, &["forest", "splat", "synth"]),
    (1, &["geom", "io", "gpu", "sfm"]),
    (0, &["progress", "stage", "rng", "testing"]),
];

/// The rooms of the binary (declared in src/main.rs); every other room is the library's.
const BINARY_ROOMS: &[&str] = &["cli", "loadbench"];

fn layer(room: &str) -> Option<u32> {
    LAYERS
        .iter()
        .find(|(_, rooms)| rooms.contains(&room))
        .map(|(l, _)| *l)
}

fn in_binary(room: &str) -> bool {
    BINARY_ROOMS.contains(&room)
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

/// How a path names a room: through `crate::` or through the library's name, `sylva::`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
enum Via {
    Crate,
    Sylva,
}

/// The rooms `text` names as `crate::<room>` or `sylva::<room>`, outside comments and test
/// code.
fn named_rooms(text: &str) -> BTreeSet<(Via, String)> {
    let mut rooms = BTreeSet::new();
    for line in text.lines() {
        let t = line.trim_start();
        if t.starts_with("#[cfg(test)]") {
            break;
        }
        if t.starts_with("//") {
            continue;
        }
        for (via, prefix) in [(Via::Crate, "crate::"), (Via::Sylva, "sylva::")] {
            let mut from = 0;
            while let Some(i) = t[from..].find(prefix) {
                let start = from + i;
                from = start + prefix.len();
                // Only a whole path segment: not `my_crate::` or `pre_sylva::`.
                let before = t[..start].chars().next_back();
                if before.is_some_and(|c| c.is_ascii_alphanumeric() || c == '_') {
                    continue;
                }
                let room: String = t[from..]
                    .chars()
                    .take_while(|c| c.is_ascii_lowercase() || *c == '_' || c.is_ascii_digit())
                    .collect();
                if !room.is_empty() {
                    rooms.insert((via, room));
                }
            }
        }
    }
    rooms
}

/// The room a source file (its path under `src/`, with `/`) belongs to; `None` for the crate
/// roots.
fn room_of(rel: &str) -> Option<&str> {
    let first = rel.split('/').next().unwrap_or("");
    let room = first.trim_end_matches(".rs");
    (!matches!(room, "lib" | "main")).then_some(room)
}

/// Every import against the flow in `files` (path under `src/`, text).
fn violations(files: &[(String, String)]) -> Vec<String> {
    let mut wrong = Vec::new();
    for (rel, text) in files {
        let Some(room) = room_of(rel) else {
            continue;
        };
        let Some(own) = layer(room) else {
            wrong.push(format!(
                "{rel}: room `{room}` is in no layer of docs/architecture.md"
            ));
            continue;
        };
        for (via, other) in named_rooms(text) {
            // The binary reaches the library only as `sylva::`; the library is one crate.
            if in_binary(room) && via == Via::Crate && !in_binary(&other) {
                wrong.push(format!(
                    "{rel}: `{room}` is the binary's and names the library's `{other}` as \
                     `crate::{other}` (write `sylva::{other}`)"
                ));
            }
            if !in_binary(room) && in_binary(&other) {
                wrong.push(format!(
                    "{rel}: `{room}` is the library's and names the binary's `{other}`"
                ));
            }
            if other == room {
                continue;
            }
            match layer(&other) {
                Some(l) if l < own => {}
                Some(l) => wrong.push(format!(
                    "{rel}: `{room}` (layer {own}) uses `{other}` (layer {l})"
                )),
                None => wrong.push(format!("{rel}: `{other}` is in no layer")),
            }
        }
    }
    wrong
}

/// The modules a crate root declares (`mod x;` / `pub mod x;`, attributes aside).
fn declared_modules(root: &str) -> BTreeSet<String> {
    root.lines()
        .map(str::trim)
        .filter(|l| !l.starts_with("//") && l.ends_with(';'))
        .filter_map(|l| {
            let l = l.strip_prefix("pub ").unwrap_or(l);
            let name = l.strip_prefix("mod ")?.trim_end_matches(';').trim();
            Some(name.to_string())
        })
        .collect()
}

#[test]
fn rooms_import_only_lower_layers() {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut paths = Vec::new();
    sources(&src, &mut paths);
    assert!(paths.len() > 100, "found only {} source files", paths.len());
    let files: Vec<(String, String)> = paths
        .iter()
        .map(|f| {
            let rel = f.strip_prefix(&src).expect("under src");
            let rel: Vec<&str> = rel.iter().filter_map(|c| c.to_str()).collect();
            (
                rel.join("/"),
                std::fs::read_to_string(f).expect("read source"),
            )
        })
        .collect();
    // The binary's rooms must be among the files read, or the binary goes unchecked.
    for room in BINARY_ROOMS {
        assert!(
            files.iter().any(|(rel, _)| room_of(rel) == Some(room)),
            "no source file of the binary's room `{room}` under src/"
        );
    }
    let wrong = violations(&files);
    assert!(
        wrong.is_empty(),
        "imports against the one-way flow:\n{}",
        wrong.join("\n")
    );
}

#[test]
fn each_crate_root_declares_its_own_rooms() {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let read = |name: &str| std::fs::read_to_string(src.join(name)).expect("read crate root");
    let lib = declared_modules(&read("lib.rs"));
    let main = declared_modules(&read("main.rs"));
    let binary: BTreeSet<String> = BINARY_ROOMS.iter().map(|r| r.to_string()).collect();
    assert_eq!(
        main, binary,
        "src/main.rs must declare exactly the binary's rooms"
    );
    let library: BTreeSet<String> = LAYERS
        .iter()
        .flat_map(|(_, rooms)| rooms.iter())
        .filter(|r| !in_binary(r))
        .map(|r| r.to_string())
        .collect();
    assert_eq!(
        lib, library,
        "src/lib.rs must declare exactly the library's rooms"
    );
}

#[test]
fn the_scanner_sees_uses_and_skips_comments_and_tests() {
    let text = "use crate::jobs::JobStore;\n// crate::api in a comment\nlet x = crate::io::read();\nlet s = sylva::store::open();\nlet y = my_crate::gc::run();\n#[cfg(test)]\nuse crate::cli;\n";
    let rooms: Vec<(Via, String)> = named_rooms(text).into_iter().collect();
    assert_eq!(
        rooms,
        [
            (Via::Crate, "io".to_string()),
            (Via::Crate, "jobs".to_string()),
            (Via::Sylva, "store".to_string()),
        ]
    );
}

#[test]
fn planted_violations_fail_the_check() {
    let files = |list: &[(&str, &str)]| -> Vec<(String, String)> {
        list.iter()
            .map(|(p, t)| (p.to_string(), t.to_string()))
            .collect()
    };
    let fine = files(&[
        (
            "cli/mod.rs",
            "use sylva::api::router;\nuse crate::loadbench::run;\n",
        ),
        ("loadbench/mod.rs", "use sylva::jobs::JobStore;\n"),
        ("pipeline/mod.rs", "use crate::io::las;\n"),
        ("main.rs", "mod cli;\n"),
    ]);
    assert_eq!(violations(&fine), Vec::<String>::new());
    for (path, text, says) in [
        (
            "io/las.rs",
            "use crate::pipeline::Stage;",
            "uses `pipeline`",
        ),
        (
            "jobs/mod.rs",
            "let b = sylva::store::open();",
            "uses `store`",
        ),
        ("loadbench/soak.rs", "use crate::cli::Cli;", "uses `cli`"),
        (
            "api/mod.rs",
            "use crate::loadbench::run;",
            "names the binary's",
        ),
        (
            "cli/run.rs",
            "use crate::api::router;",
            "write `sylva::api`",
        ),
        (
            "worker/mod.rs",
            "crate::nowhere::f();",
            "`nowhere` is in no layer",
        ),
        (
            "attic/old.rs",
            "use crate::io::las;",
            "room `attic` is in no layer",
        ),
    ] {
        let wrong = violations(&files(&[(path, text)]));
        assert!(
            wrong.iter().any(|w| w.contains(says)),
            "{path}: {text:?} should be reported ({says}); got {wrong:?}"
        );
    }
}
