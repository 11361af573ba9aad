//! The `sylva` binary: the command line (`cli`, clap) and the benchmarks it runs (`loadbench`),
//! on top of the library. Built only with the `cli` feature (on by default).

use clap::Parser;

mod cli;
mod loadbench;

fn main() -> std::process::ExitCode {
    // Mesa's Vulkan loader (lavapipe, on machines without a GPU) prints "XDG_RUNTIME_DIR is
    // invalid or not set" on every device it opens when the variable is missing, as it is in
    // containers and cron jobs; the temporary folder serves it as well.
    if std::env::var_os("XDG_RUNTIME_DIR").is_none() {
        // SAFETY: no other thread exists yet (the runtime is built below), so nothing reads
        // the environment concurrently.
        unsafe { std::env::set_var("XDG_RUNTIME_DIR", std::env::temp_dir()) };
    }
    let cli = cli::Cli::parse();
    let runtime = match tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
    {
        Ok(r) => r,
        Err(e) => {
            eprintln!("error: cannot start the async runtime: {e}");
            return std::process::ExitCode::FAILURE;
        }
    };
    match runtime.block_on(cli::main(cli)) {
        Ok(code) => code,
        Err(e) => {
            eprintln!("error: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}
