-- Myriad store schema, MySQL/MariaDB flavour. Keep in step with ../sqlite/0001_init.sql:
-- same tables, columns and meaning; only the DDL dialect differs.
-- Integers are BIGINT and floats DOUBLE because sqlx's Any driver decodes i64/f64 from
-- them on both backends. Text columns use a non-binary utf8mb4 collation: with a binary
-- one, MariaDB flags the column BINARY and sqlx returns bytes instead of text.

CREATE TABLE users (
    id            BIGINT       NOT NULL AUTO_INCREMENT PRIMARY KEY,
    -- Case-insensitive collation: usernames are unique regardless of case, as on SQLite.
    username      VARCHAR(32)  NOT NULL,
    password_hash VARCHAR(255) NOT NULL,
    created_at    BIGINT       NOT NULL,
    UNIQUE KEY users_username (username)
) ENGINE=InnoDB DEFAULT CHARSET=utf8mb4 COLLATE=utf8mb4_unicode_ci;

CREATE TABLE maps (
    id               BIGINT       NOT NULL AUTO_INCREMENT PRIMARY KEY,
    name             VARCHAR(64)  NOT NULL,
    heightmap        LONGBLOB     NULL,
    heightmap_width  BIGINT       NOT NULL DEFAULT 0,
    heightmap_height BIGINT       NOT NULL DEFAULT 0,
    heightmap_path   VARCHAR(1024) NULL,
    max_height       DOUBLE       NOT NULL,
    min_x DOUBLE NOT NULL, min_y DOUBLE NOT NULL, min_z DOUBLE NOT NULL,
    max_x DOUBLE NOT NULL, max_y DOUBLE NOT NULL, max_z DOUBLE NOT NULL,
    created_at       BIGINT       NOT NULL,
    UNIQUE KEY maps_name (name)
) ENGINE=InnoDB DEFAULT CHARSET=utf8mb4 COLLATE=utf8mb4_unicode_ci;

CREATE TABLE player_state (
    user_id    BIGINT NOT NULL,
    map_id     BIGINT NOT NULL,
    shape_kind BIGINT NOT NULL,
    radius     DOUBLE NOT NULL,
    half_x     DOUBLE NOT NULL,
    half_y     DOUBLE NOT NULL,
    half_z     DOUBLE NOT NULL,
    pos_x      DOUBLE NOT NULL,
    pos_y      DOUBLE NOT NULL,
    pos_z      DOUBLE NOT NULL,
    updated_at BIGINT NOT NULL,
    PRIMARY KEY (user_id, map_id),
    KEY player_state_map (map_id),
    CONSTRAINT player_state_user FOREIGN KEY (user_id) REFERENCES users (id) ON DELETE CASCADE,
    CONSTRAINT player_state_map FOREIGN KEY (map_id) REFERENCES maps (id) ON DELETE CASCADE
) ENGINE=InnoDB DEFAULT CHARSET=utf8mb4 COLLATE=utf8mb4_unicode_ci;

CREATE TABLE static_objects (
    map_id     BIGINT NOT NULL,
    object_id  BIGINT NOT NULL,
    shape_kind BIGINT NOT NULL,
    radius     DOUBLE NOT NULL,
    half_x     DOUBLE NOT NULL,
    half_y     DOUBLE NOT NULL,
    half_z     DOUBLE NOT NULL,
    pos_x      DOUBLE NOT NULL,
    pos_y      DOUBLE NOT NULL,
    pos_z      DOUBLE NOT NULL,
    PRIMARY KEY (map_id, object_id),
    CONSTRAINT static_objects_map FOREIGN KEY (map_id) REFERENCES maps (id) ON DELETE CASCADE
) ENGINE=InnoDB DEFAULT CHARSET=utf8mb4 COLLATE=utf8mb4_unicode_ci;
