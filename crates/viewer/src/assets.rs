//! The page's files, compiled into the library: the server answers only these names, so no
//! request path reaches the file system.

/// `(name, content type, contents)` of every asset; `index.html` is served at `/`, the others at
/// `/assets/{name}`.
pub const ASSETS: &[(&str, &str, &str)] = &[
    (
        "index.html",
        "text/html; charset=utf-8",
        include_str!("../assets/index.html"),
    ),
    (
        "viewer.js",
        "text/javascript; charset=utf-8",
        include_str!("../assets/viewer.js"),
    ),
    (
        "sort-worker.js",
        "text/javascript; charset=utf-8",
        include_str!("../assets/sort-worker.js"),
    ),
    (
        "viewer.css",
        "text/css; charset=utf-8",
        include_str!("../assets/viewer.css"),
    ),
];

/// The asset called `name`: its content type and contents.
pub fn asset(name: &str) -> Option<(&'static str, &'static str)> {
    ASSETS
        .iter()
        .find(|(n, _, _)| *n == name)
        .map(|(_, t, c)| (*t, *c))
}
