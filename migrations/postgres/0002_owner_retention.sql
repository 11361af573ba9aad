-- Owners and retention (issue 10): who created each upload and job (an opaque id derived
-- from the bearer token, '' with authentication off), for per-token quotas; and when a
-- finished job's files were removed by retention (its artifacts then answer 410 Gone).

ALTER TABLE uploads ADD COLUMN owner TEXT NOT NULL DEFAULT '';
ALTER TABLE jobs ADD COLUMN owner TEXT NOT NULL DEFAULT '';
ALTER TABLE jobs ADD COLUMN purged_at BIGINT;
CREATE INDEX uploads_owner ON uploads(owner, state);
CREATE INDEX jobs_owner ON jobs(owner, state);
CREATE INDEX jobs_finished ON jobs(finished_at) WHERE purged_at IS NULL;
CREATE INDEX uploads_expiry ON uploads(state, expires_at);
