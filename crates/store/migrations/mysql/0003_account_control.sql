-- Account control (issue 29), MySQL/MariaDB flavour. Keep in step with
-- ../sqlite/0003_account_control.sql: same columns and meaning.
ALTER TABLE users
    ADD COLUMN disabled   BIGINT       NOT NULL DEFAULT 0,
    ADD COLUMN banned_at  BIGINT       NULL,
    ADD COLUMN ban_until  BIGINT       NULL,
    ADD COLUMN ban_reason VARCHAR(255) NULL;
