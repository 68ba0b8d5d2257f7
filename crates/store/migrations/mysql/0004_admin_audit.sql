-- The admin API's audit trail (issue 29), MySQL/MariaDB flavour. Keep in step with
-- ../sqlite/0004_admin_audit.sql: same columns and meaning. Lengths are the store's
-- limits (crates/store/src/audit.rs truncates longer text before it is written).
CREATE TABLE admin_audit (
    id     BIGINT        NOT NULL AUTO_INCREMENT PRIMARY KEY,
    at     BIGINT        NOT NULL,
    actor  VARCHAR(64)   NOT NULL,
    action VARCHAR(32)   NOT NULL,
    target VARCHAR(255)  NOT NULL,
    detail VARCHAR(1024) NOT NULL,
    origin VARCHAR(64)   NOT NULL,
    ok     BIGINT        NOT NULL
) ENGINE=InnoDB DEFAULT CHARSET=utf8mb4 COLLATE=utf8mb4_unicode_ci;
