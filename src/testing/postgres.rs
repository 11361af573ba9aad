//! The low-level recipe for a throwaway PostgreSQL cluster on loopback, shared by the tests'
//! cluster (tests/common/postgres.rs) and `sylva bench load`'s (src/loadbench/postgres.rs):
//! finding the tools, `initdb` in a folder of the caller's, `pg_ctl start` on a free port of
//! 127.0.0.1 only with a socket folder of its own, trust authentication (only this machine
//! can reach it) and durability off, and `psql` as the superuser. PostgreSQL refuses to run
//! as root, so as root the server runs as the `postgres` user that Debian's package creates,
//! through `runuser`. How long the cluster lives, and where its folder comes from, is the
//! caller's.

use std::net::TcpListener;
use std::path::PathBuf;
use std::process::{Command, Stdio};

/// The operating-system user the server runs as when we are root.
pub const SERVICE_USER: &str = "postgres";
/// Ports tried before giving up (another process may take a free port before the server
/// binds it).
pub const START_TRIES: usize = 5;

/// The newest `/usr/lib/postgresql/N/bin` holding `initdb` (Debian's layout), else the
/// folder on the PATH that holds `initdb`, `pg_ctl` and `psql`.
pub fn search_bin() -> Option<PathBuf> {
    let mut versions: Vec<(u32, PathBuf)> = std::fs::read_dir("/usr/lib/postgresql")
        .into_iter()
        .flatten()
        .flatten()
        .filter_map(|e| {
            let version = e.file_name().to_str()?.parse::<u32>().ok()?;
            let bin = e.path().join("bin");
            bin.join("initdb").is_file().then_some((version, bin))
        })
        .collect();
    versions.sort();
    if let Some((_, bin)) = versions.pop() {
        return Some(bin);
    }
    let path = std::env::var_os("PATH")?;
    std::env::split_paths(&path).find(|dir| {
        ["initdb", "pg_ctl", "psql"]
            .iter()
            .all(|tool| dir.join(tool).is_file())
    })
}

/// `id -u` (or `id -u USER`), `id -g USER`: numeric ids, `None` where unknown.
fn id_of(flag: &str, user: Option<&str>) -> Option<u32> {
    let mut cmd = Command::new("id");
    cmd.arg(flag);
    if let Some(u) = user {
        cmd.arg(u);
    }
    let out = cmd.stdin(Stdio::null()).output().ok()?;
    if !out.status.success() {
        return None;
    }
    String::from_utf8_lossy(&out.stdout).trim().parse().ok()
}

/// Whether this process runs as root (and so must run the server as [`SERVICE_USER`]).
pub fn is_root() -> bool {
    id_of("-u", None) == Some(0)
}

/// The user and group ids of [`SERVICE_USER`], `None` where there is no such user.
pub fn service_user_ids() -> Option<(u32, u32)> {
    Some((
        id_of("-u", Some(SERVICE_USER))?,
        id_of("-g", Some(SERVICE_USER))?,
    ))
}

fn free_port() -> Result<u16, String> {
    TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .map(|a| a.port())
        .map_err(|e| format!("no free port on 127.0.0.1: {e}"))
}

/// Runs `cmd`, failing with its output when it exits unsuccessfully.
pub fn run(cmd: &mut Command, what: &str) -> Result<(), String> {
    let out = cmd
        .stdin(Stdio::null())
        .output()
        .map_err(|e| format!("{what}: {e}"))?;
    if out.status.success() {
        Ok(())
    } else {
        Err(format!(
            "{what} failed ({}): {}{}",
            out.status,
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        ))
    }
}

/// The tools, the folder and the superuser of one cluster: `root` holds the data folder
/// `data`, the server log and the server's socket.
pub struct Server {
    /// Folder of `initdb`, `pg_ctl` and `psql`.
    pub bin: PathBuf,
    /// The cluster's own folder.
    pub root: PathBuf,
    /// Superuser created by `initdb`.
    pub superuser: &'static str,
    /// Whether the server tools run as [`SERVICE_USER`] (we are root).
    pub as_service_user: bool,
}

impl Server {
    /// The data folder, `root/data`.
    pub fn data_dir(&self) -> PathBuf {
        self.root.join("data")
    }

    /// A command for a server tool, run as the service user when we are root.
    pub fn tool(&self, name: &str) -> Command {
        let path = self.bin.join(name);
        if self.as_service_user {
            let mut c = Command::new("runuser");
            c.args(["-u", SERVICE_USER, "--"]).arg(path);
            c
        } else {
            Command::new(path)
        }
    }

    /// `initdb` into [`Server::data_dir`]: trust authentication, UTF-8, locale C, no sync.
    pub fn init(&self) -> Result<(), String> {
        run(
            self.tool("initdb").arg("-D").arg(self.data_dir()).args([
                "-U",
                self.superuser,
                "--auth=trust",
                "--encoding=UTF8",
                "--locale=C",
                "--no-sync",
            ]),
            "initdb",
        )
    }

    /// Starts the server on a free port of 127.0.0.1, trying [`START_TRIES`] ports, and
    /// returns the port. `settings` (`-c name=value ...`) follow the fixed ones (durability
    /// off); `stdout` is where `pg_ctl`'s own output goes.
    pub fn start(&self, settings: &str, stdout: impl Fn() -> Stdio) -> Result<u16, String> {
        let mut last = String::new();
        for _ in 0..START_TRIES {
            let port = free_port()?;
            match self.pg_ctl_start(port, settings, stdout()) {
                Ok(()) => return Ok(port),
                Err(e) => last = e,
            }
        }
        Err(last)
    }

    fn pg_ctl_start(&self, port: u16, settings: &str, stdout: Stdio) -> Result<(), String> {
        let log = self.root.join("server.log");
        // Throwaway data: durability off.
        let options = format!(
            "-p {port} -c listen_addresses=127.0.0.1 -c unix_socket_directories={root} \
             -c fsync=off -c synchronous_commit=off -c full_page_writes=off {settings}",
            root = self.root.display()
        );
        run(
            self.tool("pg_ctl")
                .arg("-D")
                .arg(self.data_dir())
                .arg("-l")
                .arg(&log)
                .args(["-w", "-t", "60", "-o", &options, "start"])
                .stdout(stdout)
                .stderr(Stdio::piped()),
            "pg_ctl start",
        )
        .map_err(|e| {
            format!(
                "{e}\nserver log:\n{}",
                std::fs::read_to_string(&log).unwrap_or_default()
            )
        })
    }

    /// Runs one SQL statement as the superuser on the `postgres` database of the server
    /// listening on `port`.
    pub fn psql(&self, port: u16, sql: &str) -> Result<(), String> {
        run(
            Command::new(self.bin.join("psql"))
                .args(["-X", "-q", "-v", "ON_ERROR_STOP=1", "-h", "127.0.0.1"])
                .args(["-p", &port.to_string(), "-U", self.superuser])
                .args(["-d", "postgres", "-c", sql]),
            "psql",
        )
    }

    /// `postgres://` URL of database `name` on the server listening on `port`.
    pub fn url(&self, port: u16, name: &str) -> String {
        format!("postgres://{}@127.0.0.1:{port}/{name}", self.superuser)
    }
}
