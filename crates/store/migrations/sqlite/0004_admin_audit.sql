-- The admin API's audit trail (issue 29): every state-changing action and every refused
-- request, appended, never updated. Keep in step with ../mysql/0004_admin_audit.sql.
-- at: milliseconds since the Unix epoch. origin: the client's ip:port ("from" in the
-- API; a reserved word in SQL). ok: 1 when the action was done, 0 when refused or failed.
CREATE TABLE admin_audit (
    id     INTEGER PRIMARY KEY AUTOINCREMENT,
    at     INTEGER NOT NULL,
    actor  TEXT    NOT NULL,
    action TEXT    NOT NULL,
    target TEXT    NOT NULL,
    detail TEXT    NOT NULL,
    origin TEXT    NOT NULL,
    ok     INTEGER NOT NULL
);
