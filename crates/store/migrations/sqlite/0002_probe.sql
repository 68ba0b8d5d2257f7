-- One row rewritten by Store::check_writable at start-up: a real write (and commit)
-- proves that the database accepts writes before the server accepts players.
CREATE TABLE store_probe (
    id         INTEGER PRIMARY KEY,
    written_at INTEGER NOT NULL
);
