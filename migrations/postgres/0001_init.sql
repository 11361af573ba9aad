-- Sylva job queue and upload records (PostgreSQL): the same tables as migrations/sqlite,
-- in PostgreSQL's types. Times are BIGINT milliseconds since the Unix epoch (UTC), as in
-- SQLite, so both backends compare leases the same way; JSON documents are JSONB.

CREATE TABLE uploads (
    id            TEXT PRIMARY KEY,
    kind          TEXT NOT NULL,
    filename      TEXT NOT NULL,
    size          BIGINT NOT NULL,
    sha256        TEXT,
    part_size     BIGINT NOT NULL,
    state         TEXT NOT NULL DEFAULT 'open',
    inspection    JSONB,
    created_at    BIGINT NOT NULL,
    expires_at    BIGINT NOT NULL,
    completed_at  BIGINT
);

CREATE TABLE upload_parts (
    upload_id  TEXT NOT NULL REFERENCES uploads(id) ON DELETE CASCADE,
    n          BIGINT NOT NULL,
    size       BIGINT NOT NULL,
    sha256     TEXT NOT NULL,
    PRIMARY KEY (upload_id, n)
);

CREATE TABLE jobs (
    seq              BIGINT GENERATED ALWAYS AS IDENTITY PRIMARY KEY,
    id               TEXT NOT NULL UNIQUE,
    state            TEXT NOT NULL,
    stage            TEXT,
    progress         DOUBLE PRECISION NOT NULL DEFAULT 0,
    attempt          BIGINT NOT NULL DEFAULT 0,
    inputs           JSONB NOT NULL,
    params           JSONB NOT NULL,
    idempotency_key  TEXT UNIQUE,
    request_hash     TEXT,
    worker_id        TEXT,
    lease_until      BIGINT,
    lease_token      TEXT,
    error            JSONB,
    created_at       BIGINT NOT NULL,
    updated_at       BIGINT NOT NULL,
    started_at       BIGINT,
    finished_at      BIGINT
);
CREATE INDEX jobs_claim ON jobs(state, seq);

-- One row per stage per job; state 'done' is the checkpoint a resumed job starts after.
CREATE TABLE job_stages (
    job_id       TEXT NOT NULL REFERENCES jobs(id) ON DELETE CASCADE,
    idx          BIGINT NOT NULL,
    name         TEXT NOT NULL,
    state        TEXT NOT NULL DEFAULT 'pending',
    progress     DOUBLE PRECISION NOT NULL DEFAULT 0,
    attempt      BIGINT NOT NULL DEFAULT 0,
    started_at   BIGINT,
    finished_at  BIGINT,
    metrics      JSONB,
    PRIMARY KEY (job_id, name)
);

CREATE TABLE job_log (
    job_id   TEXT NOT NULL REFERENCES jobs(id) ON DELETE CASCADE,
    seq      BIGINT NOT NULL,
    ts       BIGINT NOT NULL,
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
    size          BIGINT NOT NULL,
    sha256        TEXT NOT NULL,
    content_type  TEXT NOT NULL,
    PRIMARY KEY (job_id, name)
);

CREATE TABLE workers (
    id          TEXT PRIMARY KEY,
    host        TEXT NOT NULL,
    pid         BIGINT NOT NULL,
    started_at  BIGINT NOT NULL,
    last_seen   BIGINT NOT NULL
);
