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

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::OnceLock;
use std::sync::atomic::{AtomicU64, Ordering};

use sylva::testing::postgres::{SERVICE_USER, Server, search_bin};

/// Superuser of the test cluster.
const SUPERUSER: &str = "sylva_test";

/// A running test cluster.
pub struct Cluster {
    server: Server,
    port: u16,
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
        url: cluster.server.url(cluster.port, &name),
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

impl Cluster {
    fn start() -> Result<Cluster, Unavailable> {
        let bin = find_bin().map_err(Unavailable::Absent)?;
        let as_service_user = sylva::testing::postgres::is_root();
        let owner = sylva::testing::postgres::service_user_ids();
        if as_service_user && owner.is_none() {
            return Err(Unavailable::Absent(format!(
                "running as root, and there is no `{SERVICE_USER}` user to run PostgreSQL as"
            )));
        }
        let root = tempfile::Builder::new()
            .prefix("sylva-test-pg-")
            .tempdir()
            .map_err(|e| Unavailable::Broken(format!("temporary folder: {e}")))?
            .keep();
        let server = Server {
            bin,
            root,
            superuser: SUPERUSER,
            as_service_user,
        };
        if let (true, Some((uid, gid))) = (as_service_user, owner) {
            std::os::unix::fs::chown(&server.root, Some(uid), Some(gid)).map_err(|e| {
                Unavailable::Broken(format!("chown {}: {e}", server.root.display()))
            })?;
        }
        server.init().map_err(Unavailable::Broken)?;
        spawn_watchdog(&server);
        // Enough connections for several `sylva` processes with a pool of 16 each.
        let port = server
            .start("-c max_connections=400 -c shared_buffers=32MB", Stdio::null)
            .map_err(Unavailable::Broken)?;
        Ok(Cluster { server, port })
    }

    /// Runs one SQL statement as the superuser on the `postgres` database.
    fn psql(&self, sql: &str) -> Result<(), String> {
        self.server.psql(self.port, sql)
    }
}

/// Stops the server and removes its folder once this test process has exited. The watchdog
/// is a separate process with no handle on our output, so test runners that wait for a
/// test's output to close are not held up by it.
fn spawn_watchdog(server: &Server) {
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
        .arg(server.data_dir())
        .arg(&server.root)
        .arg(&server.bin)
        .arg(if server.as_service_user { "yes" } else { "no" })
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn();
    if let Err(e) = spawned {
        eprintln!(
            "warning: no watchdog for the test PostgreSQL ({e}); stop it by hand: \
             pg_ctl -D {} stop",
            server.data_dir().display()
        );
    }
}

/// The cluster's root folder, for tests that look at the server log.
pub fn cluster_root() -> Option<&'static Path> {
    match CLUSTER.get() {
        Some(Ok(c)) => Some(&c.server.root),
        _ => None,
    }
}
