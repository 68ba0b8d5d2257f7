-- Account control (issue 29): an operator can disable an account or ban it, with a
-- reason and an optional end. Keep in step with ../mysql/0003_account_control.sql.
-- disabled: 0 or 1. banned_at: NULL when not banned; ban_until: NULL for a ban without
-- end. A ban is in force while banned_at IS NOT NULL and (ban_until IS NULL or
-- ban_until > now), so a timed ban ends by itself, with no job to lift it.
ALTER TABLE users ADD COLUMN disabled INTEGER NOT NULL DEFAULT 0;
ALTER TABLE users ADD COLUMN banned_at INTEGER;
ALTER TABLE users ADD COLUMN ban_until INTEGER;
ALTER TABLE users ADD COLUMN ban_reason TEXT;
