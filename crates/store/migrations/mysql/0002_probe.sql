-- One row rewritten by Store::check_writable at start-up: a real write (and commit)
-- proves that the database accepts writes before the server accepts players.
CREATE TABLE store_probe (
    id         BIGINT PRIMARY KEY,
    written_at BIGINT NOT NULL
) ENGINE = InnoDB;
