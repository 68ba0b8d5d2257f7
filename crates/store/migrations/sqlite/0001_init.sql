-- Myriad store schema, SQLite flavour. Keep in step with ../mysql/0001_init.sql:
-- same tables, columns and meaning; only the DDL dialect differs.
-- Times are milliseconds since the Unix epoch (INTEGER), floats are REAL (f64).

CREATE TABLE users (
    id            INTEGER PRIMARY KEY AUTOINCREMENT,
    -- NOCASE: usernames are unique case-insensitively, as on MariaDB (ASCII only).
    username      TEXT    NOT NULL COLLATE NOCASE UNIQUE,
    -- Argon2id PHC string; never logged.
    password_hash TEXT    NOT NULL,
    created_at    INTEGER NOT NULL
);

CREATE TABLE maps (
    id                INTEGER PRIMARY KEY AUTOINCREMENT,
    name              TEXT    NOT NULL UNIQUE,
    -- Inline heightmap: little-endian u16 samples, row-major; NULL when absent.
    heightmap         BLOB,
    heightmap_width   INTEGER NOT NULL DEFAULT 0,
    heightmap_height  INTEGER NOT NULL DEFAULT 0,
    -- Heightmap file path instead of inline samples; NULL when absent.
    heightmap_path    TEXT,
    max_height        REAL    NOT NULL,
    min_x REAL NOT NULL, min_y REAL NOT NULL, min_z REAL NOT NULL,
    max_x REAL NOT NULL, max_y REAL NOT NULL, max_z REAL NOT NULL,
    created_at        INTEGER NOT NULL
);

-- The reference's users_game_info: one row per (player, map).
CREATE TABLE player_state (
    user_id    INTEGER NOT NULL REFERENCES users(id) ON DELETE CASCADE,
    map_id     INTEGER NOT NULL REFERENCES maps(id) ON DELETE CASCADE,
    -- 0 sphere, 1 box, 2 capsule (half height in half_y).
    shape_kind INTEGER NOT NULL,
    radius     REAL    NOT NULL,
    half_x     REAL    NOT NULL,
    half_y     REAL    NOT NULL,
    half_z     REAL    NOT NULL,
    pos_x      REAL    NOT NULL,
    pos_y      REAL    NOT NULL,
    pos_z      REAL    NOT NULL,
    updated_at INTEGER NOT NULL,
    PRIMARY KEY (user_id, map_id)
);
CREATE INDEX player_state_map ON player_state (map_id);

CREATE TABLE static_objects (
    map_id     INTEGER NOT NULL REFERENCES maps(id) ON DELETE CASCADE,
    object_id  INTEGER NOT NULL,
    shape_kind INTEGER NOT NULL,
    radius     REAL    NOT NULL,
    half_x     REAL    NOT NULL,
    half_y     REAL    NOT NULL,
    half_z     REAL    NOT NULL,
    pos_x      REAL    NOT NULL,
    pos_y      REAL    NOT NULL,
    pos_z      REAL    NOT NULL,
    PRIMARY KEY (map_id, object_id)
);
