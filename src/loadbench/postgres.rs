//! A throwaway PostgreSQL cluster for `sylva bench load`, on loopback, removed when dropped.
//!
//! The same recipe as the tests' cluster (tests/common/postgres.rs): `initdb` in a fresh
//! folder under the system temporary directory, `pg_ctl start` on a free port of 127.0.0.1
//! only, a socket folder of its own, trust authentication (only this machine can reach it),
//! durability off. PostgreSQL refuses to run as root, so as root the server runs as the
//! `postgres` user that Debian's package creates, through `runuser`. Unlike the tests' cluster
//! this one lives exactly as long as its [`Cluster`] value: dropping it stops the server and
//! deletes the folder.

use std::net::TcpListener;
use std::path::PathBuf;
use std::process::{Command, Stdio};

/// Superuser of the throwaway cluster.
const SUPERUSER: &str = "sylva_bench";
/// The operating-system user the server runs as when we are root.
const SERVICE_USER: &str = "postgres";
/// Ports tried before giving up (another process may take a free port before the server
/// binds it).
const START_TRIES: usize = 5;

/// Why no cluster could be started.
#[derive(Debug, thiserror::Error)]
pub enum Unavailable {
    /// PostgreSQL is not installed here (or cannot be run as another user).
    #[error("{0}")]
    Absent(String),
    /// It is installed but did not start or answer.
    #[error("{0}")]
    Broken(String),
}

/// A running throwaway cluster; stopped and deleted on drop.
pub struct Cluster {
    bin: PathBuf,
    root: PathBuf,
    port: u16,
    as_service_user: bool,
}

/// The newest `/usr/lib/postgresql/N/bin` holding `initdb` (Debian's layout), else the
/// folder on the PATH that holds `initdb`, `pg_ctl` and `psql`.
pub fn find_bin() -> Option<PathBuf> {
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

fn free_port() -> Result<u16, String> {
    TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .map(|a| a.port())
        .map_err(|e| format!("no free port on 127.0.0.1: {e}"))
}

/// Runs `cmd`, failing with its output when it exits unsuccessfully.
fn run(cmd: &mut Command, what: &str) -> Result<(), String> {
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

impl Cluster {
    /// Initialises and starts a cluster (a few seconds).
    pub fn start() -> Result<Cluster, Unavailable> {
        let bin = find_bin().ok_or_else(|| {
            Unavailable::Absent(
                "PostgreSQL is not installed (no initdb under /usr/lib/postgresql/*/bin or on \
                 the PATH); `apt-get install postgresql`, or pass --database postgres://..."
                    .into(),
            )
        })?;
        let as_service_user = id_of("-u", None) == Some(0);
        let owner = if as_service_user {
            match (
                id_of("-u", Some(SERVICE_USER)),
                id_of("-g", Some(SERVICE_USER)),
            ) {
                (Some(uid), Some(gid)) => Some((uid, gid)),
                _ => {
                    return Err(Unavailable::Absent(format!(
                        "running as root, and there is no `{SERVICE_USER}` user to run \
                         PostgreSQL as"
                    )));
                }
            }
        } else {
            None
        };
        let root = std::env::temp_dir().join(format!(
            "sylva-bench-pg-{}-{}",
            std::process::id(),
            sylva::jobs::now_ms()
        ));
        std::fs::create_dir_all(&root)
            .map_err(|e| Unavailable::Broken(format!("{}: {e}", root.display())))?;
        // From here on, dropping `cluster` cleans up whatever was made.
        let mut cluster = Cluster {
            bin,
            root,
            port: 0,
            as_service_user,
        };
        if let Some((uid, gid)) = owner {
            std::os::unix::fs::chown(&cluster.root, Some(uid), Some(gid)).map_err(|e| {
                Unavailable::Broken(format!("chown {}: {e}", cluster.root.display()))
            })?;
        }
        cluster.init().map_err(Unavailable::Broken)?;
        let mut last = String::new();
        for _ in 0..START_TRIES {
            let port = free_port().map_err(Unavailable::Broken)?;
            match cluster.pg_ctl_start(port) {
                Ok(()) => {
                    cluster.port = port;
                    return Ok(cluster);
                }
                Err(e) => last = e,
            }
        }
        Err(Unavailable::Broken(last))
    }

    fn data_dir(&self) -> PathBuf {
        self.root.join("data")
    }

    /// A command for a server tool, run as the service user when we are root.
    fn tool(&self, name: &str) -> Command {
        let path = self.bin.join(name);
        if self.as_service_user {
            let mut c = Command::new("runuser");
            c.args(["-u", SERVICE_USER, "--"]).arg(path);
            c
        } else {
            Command::new(path)
        }
    }

    fn init(&self) -> Result<(), String> {
        run(
            self.tool("initdb").arg("-D").arg(self.data_dir()).args([
                "-U",
                SUPERUSER,
                "--auth=trust",
                "--encoding=UTF8",
                "--locale=C",
                "--no-sync",
            ]),
            "initdb",
        )
    }

    fn pg_ctl_start(&self, port: u16) -> Result<(), String> {
        let log = self.root.join("server.log");
        // Throwaway data: durability off; enough connections for a pool of 16 and psql.
        let options = format!(
            "-p {port} -c listen_addresses=127.0.0.1 -c unix_socket_directories={root} \
             -c fsync=off -c synchronous_commit=off -c full_page_writes=off \
             -c max_connections=100",
            root = self.root.display()
        );
        run(
            self.tool("pg_ctl")
                .arg("-D")
                .arg(self.data_dir())
                .arg("-l")
                .arg(&log)
                .args(["-w", "-t", "60", "-o", &options, "start"]),
            "pg_ctl start",
        )
        .map_err(|e| {
            format!(
                "{e}\nserver log:\n{}",
                std::fs::read_to_string(&log).unwrap_or_default()
            )
        })
    }

    /// Creates database `name` (an SQL identifier chosen by the caller, not user input) and
    /// returns its `postgres://` URL.
    pub fn create_database(&self, name: &str) -> Result<String, Unavailable> {
        run(
            Command::new(self.bin.join("psql"))
                .args(["-X", "-q", "-v", "ON_ERROR_STOP=1", "-h", "127.0.0.1"])
                .args(["-p", &self.port.to_string(), "-U", SUPERUSER])
                .args(["-d", "postgres", "-c", &format!("CREATE DATABASE {name}")]),
            "psql",
        )
        .map_err(Unavailable::Broken)?;
        Ok(format!(
            "postgres://{SUPERUSER}@127.0.0.1:{}/{name}",
            self.port
        ))
    }

    /// The tools' version as `pg_ctl --version` prints it, e.g. `15.14`; empty where unknown.
    pub fn version(&self) -> String {
        Command::new(self.bin.join("pg_ctl"))
            .arg("--version")
            .output()
            .ok()
            .and_then(|o| {
                // `pg_ctl (PostgreSQL) 15.14 (Debian 15.14-0+deb12u1)`: the word after the name.
                let text = String::from_utf8_lossy(&o.stdout).into_owned();
                let mut words = text.split_whitespace();
                words.find(|w| *w == "(PostgreSQL)")?;
                words.next().map(str::to_string)
            })
            .unwrap_or_default()
    }
}

impl Drop for Cluster {
    fn drop(&mut self) {
        if self.port != 0 {
            let _ = run(
                self.tool("pg_ctl").arg("-D").arg(self.data_dir()).args([
                    "-m",
                    "immediate",
                    "stop",
                ]),
                "pg_ctl stop",
            );
        }
        let _ = std::fs::remove_dir_all(&self.root);
    }
}
