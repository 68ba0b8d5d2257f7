//! The web console's files (a placeholder page until the console lands: h13 replaces
//! this file wholesale).

/// The console file at `path` (`index.html` for `/`, else the part after `/console/`):
/// its content type and bytes, or `None`.
pub fn asset(path: &str) -> Option<(&'static str, &'static [u8])> {
    match path {
        "index.html" => Some((
            "text/html; charset=utf-8",
            b"<!doctype html><title>Myriad admin</title><p>The Myriad admin API is at <code>/api</code>.</p>\n",
        )),
        _ => None,
    }
}
