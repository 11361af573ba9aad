-- Tenancy (issue 25): API keys as records, and webhook secrets that rotate one owner at a time.

-- A managed API key. Only the SHA-256 of the key is kept; the key itself is shown once, when
-- it is created. The records it owns carry its id as their owner id.
CREATE TABLE api_keys (
    id           TEXT PRIMARY KEY,
    name         TEXT NOT NULL UNIQUE,
    -- Hex SHA-256 of the whole key.
    hash         TEXT NOT NULL UNIQUE,
    -- The key's first characters, to recognise it in lists (never enough to use it).
    prefix       TEXT NOT NULL,
    admin        BIGINT NOT NULL DEFAULT 0,
    -- Per-key quotas (NULL: the server's --quota-jobs / --quota-bytes).
    quota_jobs   BIGINT,
    quota_bytes  BIGINT,
    created_at   BIGINT NOT NULL,
    expires_at   BIGINT,
    revoked_at   BIGINT
);

-- Webhook secret generation per owner: secrets are derived from the server key, the owner id
-- and the generation; rotation bumps the generation and keeps the previous secret valid for
-- deliveries until `previous_until` (Unix ms).
CREATE TABLE webhook_secrets (
    owner           TEXT PRIMARY KEY,
    generation      BIGINT NOT NULL,
    rotated_at      BIGINT NOT NULL,
    previous_until  BIGINT NOT NULL
);
