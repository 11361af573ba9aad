-- Webhooks (issue 10): a job may name a URL to notify; each notification is a row of the
-- outbox below, written in the same transaction as the state change it reports, so a crash
-- loses none. Dispatchers (in `sylva serve` and `sylva worker`) claim due rows with a lease,
-- POST them signed, and reschedule failures with exponential backoff.

ALTER TABLE jobs ADD COLUMN webhook TEXT;

CREATE TABLE webhook_deliveries (
    seq              INTEGER PRIMARY KEY AUTOINCREMENT,
    id               TEXT NOT NULL UNIQUE,
    job_id           TEXT NOT NULL,
    owner            TEXT NOT NULL,
    url              TEXT NOT NULL,
    event            TEXT NOT NULL,
    -- The exact bytes sent (and signed) on every attempt.
    body             TEXT NOT NULL,
    -- pending | delivered | failed
    state            TEXT NOT NULL DEFAULT 'pending',
    attempts         INTEGER NOT NULL DEFAULT 0,
    next_attempt_at  INTEGER NOT NULL,
    lease_until      INTEGER,
    lease_token      TEXT,
    last_status      INTEGER,
    last_error       TEXT,
    created_at       INTEGER NOT NULL,
    updated_at       INTEGER NOT NULL,
    finished_at      INTEGER
);
CREATE INDEX webhook_deliveries_due ON webhook_deliveries(next_attempt_at) WHERE state = 'pending';
CREATE INDEX webhook_deliveries_job ON webhook_deliveries(job_id, seq);

-- Server-wide values every process must agree on (the webhook signing key when none is
-- configured), created once by whichever process needs one first.
CREATE TABLE settings (
    name   TEXT PRIMARY KEY,
    value  TEXT NOT NULL
);
