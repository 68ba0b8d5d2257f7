//! The web console's files, shipped inside the binary (no build step, nothing fetched
//! from elsewhere at run time).
//!
//! The admin listener serves them without a token: they hold no data. The page reads
//! the token from its URL fragment (`#token=…`, which a browser never sends) or from an
//! input, and calls the JSON routes with it in the `Authorization` header.
//!
//! The files are a fixed table: a request path is looked up, never joined to a
//! directory, so no path reaches anything else.

/// The page itself.
const INDEX_HTML: &[u8] = include_bytes!("console/index.html");
/// Polling, drawing and the kick and ban actions.
const CONSOLE_JS: &[u8] = include_bytes!("console/console.js");
/// The page's style.
const CONSOLE_CSS: &[u8] = include_bytes!("console/console.css");

/// Content type of HTML.
const HTML: &str = "text/html; charset=utf-8";
/// Content type of JavaScript.
const JAVASCRIPT: &str = "text/javascript; charset=utf-8";
/// Content type of CSS.
const CSS: &str = "text/css; charset=utf-8";

/// Every file under `console/`, by name.
const FILES: [(&str, &str, &[u8]); 2] = [("console.js", JAVASCRIPT, CONSOLE_JS), ("console.css", CSS, CONSOLE_CSS)];

/// The content type and bytes of the console's file at `path`: the page for `/`, its
/// script and style for `/console/console.js` and `/console/console.css`. `path` is the
/// request path (with or without its leading `/`) or, as the admin router passes it,
/// the file's name alone (`index.html` for `/`, `console.js` for `/console/console.js`).
/// Anything else is `None` (a 404).
pub fn asset(path: &str) -> Option<(&'static str, &'static [u8])> {
    let path = path.strip_prefix('/').unwrap_or(path);
    let name = path.strip_prefix("console/").unwrap_or(path);
    if name.is_empty() || name == "index.html" {
        return Some((HTML, INDEX_HTML));
    }
    FILES.iter().find(|(file, _, _)| *file == name).map(|&(_, kind, bytes)| (kind, bytes))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_page_and_its_files_are_served_with_their_types() {
        for path in ["/", "", "index.html"] {
            let (kind, bytes) = asset(path).unwrap();
            assert_eq!(kind, HTML);
            assert!(std::str::from_utf8(bytes).unwrap().starts_with("<!doctype html>"));
        }
        assert_eq!(asset("/console/console.js").unwrap().0, JAVASCRIPT);
        assert_eq!(asset("console/console.js").unwrap().0, JAVASCRIPT);
        assert_eq!(asset("console.js").unwrap().0, JAVASCRIPT);
        assert_eq!(asset("/console/console.css").unwrap().0, CSS);
        assert_eq!(asset("console.css").unwrap().0, CSS);
        assert_eq!(asset("console.css").unwrap().1, CONSOLE_CSS);
    }

    #[test]
    fn nothing_outside_the_table_is_served() {
        for path in [
            "//",
            "/console",
            "console.rs",
            "/console/../Cargo.toml",
            "../console.rs",
            "console/console/console.js",
            "/console/./console.js",
            "/console/console.js/",
            "/console/CONSOLE.JS",
            "/console//console.js",
            "/console/%2e%2e/lib.rs",
            "/api/state",
            "/../console.rs",
        ] {
            assert!(asset(path).is_none(), "{path} is not a console file");
        }
    }

    #[test]
    fn the_page_loads_only_files_of_the_table_and_nothing_from_elsewhere() {
        let page = std::str::from_utf8(INDEX_HTML).unwrap();
        let mut linked = 0;
        for attr in ["src=\"", "href=\""] {
            for (at, _) in page.match_indices(attr) {
                let rest = &page[at + attr.len()..];
                let target = &rest[..rest.find('"').unwrap()];
                assert!(asset(target).is_some(), "the page links {target}, which is not served");
                linked += 1;
            }
        }
        assert_eq!(linked, FILES.len(), "the page links its script and its style");
        for (name, bytes) in [("index.html", INDEX_HTML), ("console.js", CONSOLE_JS), ("console.css", CONSOLE_CSS)] {
            let text = std::str::from_utf8(bytes).unwrap();
            for remote in ["http://", "https://", "//cdn", "@import", "url("] {
                assert!(!text.contains(remote), "{name} refers to something outside the binary ({remote})");
            }
        }
    }

    #[test]
    fn the_token_never_goes_into_a_request_address() {
        let script = std::str::from_utf8(CONSOLE_JS).unwrap();
        // It travels in the Authorization header only, and the fragment is dropped from
        // the address once read.
        assert!(script.contains("Authorization: \"Bearer \" + state.token"));
        assert!(script.contains("history.replaceState"));
        assert!(!script.contains("?token") && !script.contains("&token"));
    }
}
