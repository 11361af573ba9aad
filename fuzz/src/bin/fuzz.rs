//! The AFL++ harness: `SYLVA_FUZZ_TARGET=<target> cargo afl fuzz -i corpus/<target> -o out
//! target/release/fuzz` (the targets: `sylva::pipeline::fuzz::TARGETS`). Each input runs in
//! this process (AFL's persistent mode); a panic that leaves the target aborts, which AFL
//! records as a crash. Without afl.rs's panic hook (`fuzz_nohook!`), a panic Sylva catches
//! and reports as the file's fault (the LAZ decoder's, `io::las`) is not one.

fn main() {
    let target = std::env::var("SYLVA_FUZZ_TARGET").unwrap_or_default();
    if !sylva::pipeline::fuzz::TARGETS.contains(&target.as_str()) {
        eprintln!(
            "set SYLVA_FUZZ_TARGET to one of: {}",
            sylva::pipeline::fuzz::TARGETS.join(", ")
        );
        std::process::exit(2);
    }
    // Scratch files in memory where there is a tmpfs.
    let base = if std::path::Path::new("/dev/shm").is_dir() {
        std::path::PathBuf::from("/dev/shm")
    } else {
        std::env::temp_dir()
    };
    let scratch = tempfile::Builder::new()
        .prefix("sylva-fuzz-")
        .tempdir_in(base)
        .unwrap_or_else(|e| panic!("scratch folder: {e}"));
    afl::fuzz_nohook!(|data: &[u8]| {
        let _ = sylva::pipeline::fuzz::run(&target, data, scratch.path());
    });
}
