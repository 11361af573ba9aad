-- Sylva job queue and upload records (SQLite, WAL).
-- Times are integer milliseconds since the Unix epoch (UTC).

CREATE TABLE uploads (
    id            TEXT PRIMARY KEY,
    kind          TEXT NOT NULL,
    filename      TEXT NOT NULL,
    size          INTEGER NOT NULL,
    sha256        TEXT,
    part_size     INTEGER NOT NULL,
    state         TEXT NOT NULL DEFAULT 'open',
    inspection    TEXT,
    created_at    INTEGER NOT NULL,
    expires_at    INTEGER NOT NULL,
    completed_at  INTEGER
);

CREATE TABLE upload_parts (
    upload_id  TEXT NOT NULL REFERENCES uploads(id) ON DELETE CASCADE,
    n          INTEGER NOT NULL,
    size       INTEGER NOT NULL,
    sha256     TEXT NOT NULL,
    PRIMARY KEY (upload_id, n)
);

CREATE TABLE jobs (
    seq              INTEGER PRIMARY KEY AUTOINCREMENT,
    id               TEXT NOT NULL UNIQUE,
    state            TEXT NOT NULL,
    stage            TEXT,
    progress         REAL NOT NULL DEFAULT 0,
    attempt          INTEGER NOT NULL DEFAULT 0,
    inputs           TEXT NOT NULL,
    params           TEXT NOT NULL,
    idempotency_key  TEXT UNIQUE,
    request_hash     TEXT,
    worker_id        TEXT,
    lease_until      INTEGER,
    lease_token      TEXT,
    error            TEXT,
    created_at       INTEGER NOT NULL,
    updated_at       INTEGER NOT NULL,
    started_at       INTEGER,
    finished_at      INTEGER
);
CREATE INDEX jobs_claim ON jobs(state, seq);

-- One row per stage per job; state 'done' is the checkpoint a resumed job starts after.
CREATE TABLE job_stages (
    job_id       TEXT NOT NULL REFERENCES jobs(id) ON DELETE CASCADE,
    idx          INTEGER NOT NULL,
    name         TEXT NOT NULL,
    state        TEXT NOT NULL DEFAULT 'pending',
    progress     REAL NOT NULL DEFAULT 0,
    attempt      INTEGER NOT NULL DEFAULT 0,
    started_at   INTEGER,
    finished_at  INTEGER,
    metrics      TEXT,
    PRIMARY KEY (job_id, name)
);

CREATE TABLE job_log (
    job_id   TEXT NOT NULL REFERENCES jobs(id) ON DELETE CASCADE,
    seq      INTEGER NOT NULL,
    ts       INTEGER NOT NULL,
    level    TEXT NOT NULL,
    stage    TEXT,
    message  TEXT NOT NULL,
    PRIMARY KEY (job_id, seq)
);

CREATE TABLE artifacts (
    job_id        TEXT NOT NULL REFERENCES jobs(id) ON DELETE CASCADE,
    name          TEXT NOT NULL,
    stage         TEXT NOT NULL,
    kind          TEXT NOT NULL,
    size          INTEGER NOT NULL,
    sha256        TEXT NOT NULL,
    content_type  TEXT NOT NULL,
    PRIMARY KEY (job_id, name)
);

CREATE TABLE workers (
    id          TEXT PRIMARY KEY,
    host        TEXT NOT NULL,
    pid         INTEGER NOT NULL,
    started_at  INTEGER NOT NULL,
    last_seen   INTEGER NOT NULL
);
