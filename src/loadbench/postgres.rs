//! A throwaway PostgreSQL cluster for `sylva bench load`, on loopback, removed when dropped.
//!
//! The same recipe as the tests' cluster (tests/common/postgres.rs), shared with it in
//! [`sylva::testing::postgres`]: `initdb` in a fresh folder under the system temporary
//! directory, `pg_ctl start` on a free port of 127.0.0.1 only, a socket folder of its own,
//! trust authentication (only this machine can reach it), durability off. PostgreSQL refuses
//! to run as root, so as root the server runs as the `postgres` user that Debian's package
//! creates, through `runuser`. Unlike the tests' cluster this one lives exactly as long as its
//! [`Cluster`] value: dropping it stops the server and deletes the folder.

use std::process::{Command, Stdio};

use sylva::testing::postgres::{SERVICE_USER, Server, run, search_bin};

/// Superuser of the throwaway cluster.
const SUPERUSER: &str = "sylva_bench";

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
    server: Server,
    port: u16,
}

impl Cluster {
    /// Initialises and starts a cluster (a few seconds).
    pub fn start() -> Result<Cluster, Unavailable> {
        let bin = search_bin().ok_or_else(|| {
            Unavailable::Absent(
                "PostgreSQL is not installed (no initdb under /usr/lib/postgresql/*/bin or on \
                 the PATH); `apt-get install postgresql`, or pass --database postgres://..."
                    .into(),
            )
        })?;
        let as_service_user = sylva::testing::postgres::is_root();
        let owner = if as_service_user {
            match sylva::testing::postgres::service_user_ids() {
                Some(ids) => Some(ids),
                None => {
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
            server: Server {
                bin,
                root,
                superuser: SUPERUSER,
                as_service_user,
            },
            port: 0,
        };
        if let Some((uid, gid)) = owner {
            let root = &cluster.server.root;
            std::os::unix::fs::chown(root, Some(uid), Some(gid))
                .map_err(|e| Unavailable::Broken(format!("chown {}: {e}", root.display())))?;
        }
        cluster.server.init().map_err(Unavailable::Broken)?;
        // Enough connections for a pool of 16 and psql.
        cluster.port = cluster
            .server
            .start("-c max_connections=100", Stdio::piped)
            .map_err(Unavailable::Broken)?;
        Ok(cluster)
    }

    /// Creates database `name` (an SQL identifier chosen by the caller, not user input) and
    /// returns its `postgres://` URL.
    pub fn create_database(&self, name: &str) -> Result<String, Unavailable> {
        self.server
            .psql(self.port, &format!("CREATE DATABASE {name}"))
            .map_err(Unavailable::Broken)?;
        Ok(self.server.url(self.port, name))
    }

    /// The tools' version as `pg_ctl --version` prints it, e.g. `15.14`; empty where unknown.
    pub fn version(&self) -> String {
        Command::new(self.server.bin.join("pg_ctl"))
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
                self.server
                    .tool("pg_ctl")
                    .arg("-D")
                    .arg(self.server.data_dir())
                    .args(["-m", "immediate", "stop"]),
                "pg_ctl stop",
            );
        }
        let _ = std::fs::remove_dir_all(&self.server.root);
    }
}
