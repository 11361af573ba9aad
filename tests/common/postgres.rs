//! A throwaway PostgreSQL server for tests, on loopback, with one fresh database per test.
//!
//! The first test that asks for a database starts a private cluster: `initdb` in a temporary
//! folder, `pg_ctl start` on a free port of 127.0.0.1 (no other address, a socket folder of
//! its own, trust authentication since only this machine can reach it, no fsync). PostgreSQL
//! refuses to run as root, so as root the server runs as the `postgres` user (which Debian's
//! package creates) through `runuser`. Every test then gets its own database, dropped when the
//! test ends. A watchdog process stops the cluster and removes its folder once the test
//! process has exited, whether it ended normally, panicked or was killed.
//!
//! Where PostgreSQL is not installed (no `initdb` under /usr/lib/postgresql/*/bin nor on the
//! PATH), [`database`] prints why and returns `None`, and the caller skips its PostgreSQL
//! case. Where it is installed but does not start, the test fails with the server's log.
//! `SYLVA_TEST_POSTGRES_BIN` overrides the search: a folder holding `initdb`, `pg_ctl` and
//! `psql`, or `none` to skip the PostgreSQL cases.
//!
//! This file is shared: tests/common includes it for the integration tests, and the library's
//! unit tests include it by path.
#![allow(dead_code)]

use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::OnceLock;
use std::sync::atomic::{AtomicU64, Ordering};

/// Superuser of the test cluster.
const SUPERUSER: &str = "sylva_test";
/// The operating-system user the server runs as when the tests run as root.
const SERVICE_USER: &str = "postgres";
/// Ports tried before giving up (another process may take a free port before we bind it).
const START_TRIES: usize = 5;

/// A running test cluster.
pub struct Cluster {
    bin: PathBuf,
    port: u16,
    root: PathBuf,
}

/// One database of the test cluster, dropped (with its connections) when this is dropped.
pub struct TestDatabase {
    /// `postgres://` URL of the database.
    pub url: String,
    name: String,
    cluster: &'static Cluster,
}

impl Drop for TestDatabase {
    fn drop(&mut self) {
        let sql = format!("DROP DATABASE IF EXISTS {} WITH (FORCE)", self.name);
        let _ = self.cluster.psql(&sql);
    }
}

enum Unavailable {
    /// PostgreSQL is not installed here: skip.
    Absent(String),
    /// It is installed but did not start: fail.
    Broken(String),
}

static CLUSTER: OnceLock<Result<Cluster, Unavailable>> = OnceLock::new();
static NEXT_DB: AtomicU64 = AtomicU64::new(0);

/// A fresh, empty database on the test cluster (started on first use), or `None` with the
/// reason printed when PostgreSQL is not installed.
pub fn database() -> Option<TestDatabase> {
    let cluster = match CLUSTER.get_or_init(Cluster::start) {
        Ok(c) => c,
        Err(Unavailable::Absent(why)) => {
            sylva::testing::skip("postgres", &format!("the PostgreSQL case: {why}"));
            return None;
        }
        Err(Unavailable::Broken(why)) => panic!("the test PostgreSQL did not start: {why}"),
    };
    let name = format!(
        "sylva_{}_{}",
        std::process::id(),
        NEXT_DB.fetch_add(1, Ordering::Relaxed)
    );
    if let Err(e) = cluster.psql(&format!("CREATE DATABASE {name}")) {
        panic!("cannot create test database {name}: {e}");
    }
    Some(TestDatabase {
        url: format!("postgres://{SUPERUSER}@127.0.0.1:{}/{name}", cluster.port),
        name,
        cluster,
    })
}

/// Environment variable naming the folder of the PostgreSQL tools, or `none`.
const BIN_VAR: &str = "SYLVA_TEST_POSTGRES_BIN";

/// The folder holding `initdb`, `pg_ctl` and `psql`: `$SYLVA_TEST_POSTGRES_BIN`, else the
/// newest /usr/lib/postgresql/N/bin (Debian's layout), else wherever they are on the PATH.
fn find_bin() -> Result<PathBuf, String> {
    const MISSING: &str = "PostgreSQL is not installed (no initdb under \
                           /usr/lib/postgresql/*/bin or on the PATH); `apt-get install \
                           postgresql` to run it";
    match std::env::var_os(BIN_VAR) {
        Some(v) if v == "none" => Err(format!("{BIN_VAR}=none")),
        Some(v) => {
            let dir = PathBuf::from(v);
            if dir.join("initdb").is_file() {
                Ok(dir)
            } else {
                Err(format!("{BIN_VAR}={} holds no initdb", dir.display()))
            }
        }
        None => search_bin().ok_or_else(|| MISSING.to_string()),
    }
}

fn search_bin() -> Option<PathBuf> {
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

fn is_root() -> bool {
    Command::new("id")
        .arg("-u")
        .output()
        .map(|o| String::from_utf8_lossy(&o.stdout).trim() == "0")
        .unwrap_or(false)
}

/// `id -u USER` and `id -g USER`.
fn user_ids(user: &str) -> Option<(u32, u32)> {
    let id = |flag: &str| -> Option<u32> {
        let out = Command::new("id").arg(flag).arg(user).output().ok()?;
        if !out.status.success() {
            return None;
        }
        String::from_utf8_lossy(&out.stdout).trim().parse().ok()
    };
    Some((id("-u")?, id("-g")?))
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
    fn start() -> Result<Cluster, Unavailable> {
        let bin = find_bin().map_err(Unavailable::Absent)?;
        let as_service_user = is_root();
        if as_service_user && user_ids(SERVICE_USER).is_none() {
            return Err(Unavailable::Absent(format!(
                "running as root, and there is no `{SERVICE_USER}` user to run PostgreSQL as"
            )));
        }
        let root = tempfile::Builder::new()
            .prefix("sylva-test-pg-")
            .tempdir()
            .map_err(|e| Unavailable::Broken(format!("temporary folder: {e}")))?
            .keep();
        let cluster = Cluster { bin, port: 0, root };
        cluster.init(as_service_user).map_err(Unavailable::Broken)?;
        cluster.spawn_watchdog(as_service_user);
        let mut last = String::new();
        for _ in 0..START_TRIES {
            let port = free_port().map_err(Unavailable::Broken)?;
            match cluster.pg_ctl_start(as_service_user, port) {
                Ok(()) => {
                    return Ok(Cluster { port, ..cluster });
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
    fn tool(&self, name: &str, as_service_user: bool) -> Command {
        let path = self.bin.join(name);
        if as_service_user {
            let mut c = Command::new("runuser");
            c.args(["-u", SERVICE_USER, "--"]).arg(path);
            c
        } else {
            Command::new(path)
        }
    }

    fn init(&self, as_service_user: bool) -> Result<(), String> {
        if as_service_user {
            let (uid, gid) =
                user_ids(SERVICE_USER).ok_or_else(|| format!("no `{SERVICE_USER}` user"))?;
            std::os::unix::fs::chown(&self.root, Some(uid), Some(gid))
                .map_err(|e| format!("chown {}: {e}", self.root.display()))?;
        }
        run(
            self.tool("initdb", as_service_user)
                .arg("-D")
                .arg(self.data_dir())
                .args([
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

    fn pg_ctl_start(&self, as_service_user: bool, port: u16) -> Result<(), String> {
        let log = self.root.join("server.log");
        // Throwaway data: durability off for speed; enough connections for several
        // `sylva` processes with a pool of 16 each.
        let options = format!(
            "-p {port} -c listen_addresses=127.0.0.1 -c unix_socket_directories={root} \
             -c fsync=off -c synchronous_commit=off -c full_page_writes=off \
             -c max_connections=400 -c shared_buffers=32MB",
            root = self.root.display()
        );
        let started = run(
            self.tool("pg_ctl", as_service_user)
                .arg("-D")
                .arg(self.data_dir())
                .arg("-l")
                .arg(&log)
                .args(["-w", "-t", "60", "-o", &options, "start"])
                .stdout(Stdio::null())
                .stderr(Stdio::piped()),
            "pg_ctl start",
        );
        started.map_err(|e| {
            format!(
                "{e}\nserver log:\n{}",
                std::fs::read_to_string(&log).unwrap_or_default()
            )
        })
    }

    /// Stops the server and removes its folder once this test process has exited. The
    /// watchdog is a separate process with no handle on our output, so test runners that
    /// wait for a test's output to close are not held up by it.
    fn spawn_watchdog(&self, as_service_user: bool) {
        let script = r#"
            while [ -d "/proc/$1" ]; do sleep 1; done
            if [ "$5" = yes ]; then
                runuser -u postgres -- "$4/pg_ctl" -D "$2" stop -m immediate
            else
                "$4/pg_ctl" -D "$2" stop -m immediate
            fi
            rm -rf "$3"
        "#;
        let spawned = Command::new("sh")
            .arg("-c")
            .arg(script)
            .arg("sylva-test-pg-watchdog")
            .arg(std::process::id().to_string())
            .arg(self.data_dir())
            .arg(&self.root)
            .arg(&self.bin)
            .arg(if as_service_user { "yes" } else { "no" })
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn();
        if let Err(e) = spawned {
            eprintln!(
                "warning: no watchdog for the test PostgreSQL ({e}); stop it by hand: \
                 pg_ctl -D {} stop",
                self.data_dir().display()
            );
        }
    }

    /// Runs one SQL statement as the superuser on the `postgres` database.
    fn psql(&self, sql: &str) -> Result<(), String> {
        run(
            Command::new(self.bin.join("psql"))
                .args(["-X", "-q", "-v", "ON_ERROR_STOP=1", "-h", "127.0.0.1"])
                .args([
                    "-p",
                    &self.port.to_string(),
                    "-U",
                    SUPERUSER,
                    "-d",
                    "postgres",
                ])
                .args(["-c", sql]),
            "psql",
        )
    }
}

/// The cluster's root folder, for tests that look at the server log.
pub fn cluster_root() -> Option<&'static Path> {
    match CLUSTER.get() {
        Some(Ok(c)) => Some(&c.root),
        _ => None,
    }
}
