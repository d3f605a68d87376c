//! The modules of each crate import one another without circles.
//!
//! A module is a source file (`lib.rs` and `main.rs` are the crate root, `a/mod.rs` is module
//! `a`, `a/b.rs` is `a::b`) or an inline `mod name { .. }` in one. Every path a module names
//! through `crate::`, `super::` or `self::` (in `use` declarations, their `{..}` groups
//! included, and in expressions and types) is resolved to the module that holds the item,
//! following the `use` re-exports of the modules on the way (`crate::Splats` is the module
//! `lib.rs` re-exports it from). A reference from module `a::x` to module `b::y` is an edge
//! between the two children, `a` and `b`, of their deepest common parent (here the crate root);
//! each folder's children form one graph. A circle in one of these graphs means two parts of a
//! crate cannot be read, tested or moved one without the other, and is reported with the
//! `file:line` of every edge on it.
//!
//! Not counted: comments, string literals, paths outside the crate, and `#[cfg(test)]` modules
//! (a module's tests may use anything).
//!
//! The checker reads the sources as text and needs no dependency; it knows the layout rustfmt
//! gives (an inline module closes with a `}` at the indentation of its `mod` line).

use std::collections::{BTreeMap, BTreeSet, VecDeque};
use std::fmt;
use std::path::{Path, PathBuf};

/// A module path below the crate root (`[]` is the root).
type ModPath = Vec<String>;

/// Where an edge was seen: the file (relative to the crate's `src`), its line and the path.
#[derive(Clone, Debug)]
struct Site {
    file: String,
    line: usize,
    path: String,
}

/// The references among the children of one module: from child, to child, first site.
type Graph = BTreeMap<String, BTreeMap<String, Site>>;

/// A circle among the children of one module.
#[derive(Debug)]
struct Circle {
    /// The module whose children form the circle (`crate` for the root).
    parent: String,
    /// Every module of the strongly connected set.
    members: Vec<String>,
    /// One circle through them, as edges `from -> to` with the first place each was seen.
    edges: Vec<(String, String, Site)>,
    /// The other imports among them, in the same form.
    others: Vec<(String, String, Site)>,
}

impl fmt::Display for Circle {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let names: Vec<&str> = self.edges.iter().map(|(a, _, _)| a.as_str()).collect();
        writeln!(
            f,
            "  in `{}`: {} -> {} (modules in the circle: {})",
            self.parent,
            names.join(" -> "),
            names[0],
            self.members.join(", ")
        )?;
        let line = |f: &mut fmt::Formatter<'_>, (from, to, site): &(String, String, Site)| {
            writeln!(
                f,
                "    {from} -> {to}: src/{}:{} `{}`",
                site.file, site.line, site.path
            )
        };
        for edge in &self.edges {
            line(f, edge)?;
        }
        if !self.others.is_empty() {
            writeln!(f, "    other imports among them:")?;
            for edge in &self.others {
                line(f, edge)?;
            }
        }
        Ok(())
    }
}

/// The source text with comments and the contents of string and character literals replaced
/// by spaces, line structure kept.
fn code_only(text: &str) -> String {
    let c: Vec<char> = text.chars().collect();
    let mut out = String::with_capacity(text.len());
    let ident = |ch: char| ch.is_alphanumeric() || ch == '_';
    let blank = |out: &mut String, ch: char| out.push(if ch == '\n' { '\n' } else { ' ' });
    let mut i = 0;
    while i < c.len() {
        let prev = if i > 0 { c[i - 1] } else { ' ' };
        if c[i] == '/' && c.get(i + 1) == Some(&'/') {
            while i < c.len() && c[i] != '\n' {
                i += 1;
                out.push(' ');
            }
        } else if c[i] == '/' && c.get(i + 1) == Some(&'*') {
            let mut depth = 0;
            while i < c.len() {
                if c[i] == '/' && c.get(i + 1) == Some(&'*') {
                    depth += 1;
                    out.push_str("  ");
                    i += 2;
                } else if c[i] == '*' && c.get(i + 1) == Some(&'/') {
                    depth -= 1;
                    out.push_str("  ");
                    i += 2;
                    if depth == 0 {
                        break;
                    }
                } else {
                    blank(&mut out, c[i]);
                    i += 1;
                }
            }
        } else if let Some(hashes) = raw_string_at(&c, i).filter(|_| !ident(prev)) {
            out.push('r');
            out.extend(std::iter::repeat_n('#', hashes));
            out.push('"');
            i += 2 + hashes;
            while i < c.len() {
                if c[i] == '"' && c[i + 1..].iter().take_while(|&&h| h == '#').count() >= hashes {
                    out.push('"');
                    out.extend(std::iter::repeat_n('#', hashes));
                    i += 1 + hashes;
                    break;
                }
                blank(&mut out, c[i]);
                i += 1;
            }
        } else if c[i] == '"' {
            out.push('"');
            i += 1;
            while i < c.len() && c[i] != '"' {
                if c[i] == '\\' {
                    out.push(' ');
                    i += 1;
                }
                if i < c.len() {
                    blank(&mut out, c[i]);
                    i += 1;
                }
            }
            out.push('"');
            i += 1;
        } else if c[i] == '\'' && (c.get(i + 1) == Some(&'\\') || c.get(i + 2) == Some(&'\'')) {
            // A character literal (a lifetime or a label has no closing quote after one char).
            out.push('\'');
            i += 1;
            if c.get(i) == Some(&'\\') {
                out.push_str("  ");
                i += 2;
            }
            while i < c.len() && c[i] != '\'' {
                blank(&mut out, c[i]);
                i += 1;
            }
            out.push('\'');
            i += 1;
        } else {
            out.push(c[i]);
            i += 1;
        }
    }
    out
}

/// The number of `#` of the raw string literal whose `r` is `c[i]`, if one starts there.
fn raw_string_at(c: &[char], i: usize) -> Option<usize> {
    if c[i] != 'r' {
        return None;
    }
    let hashes = c[i + 1..].iter().take_while(|&&h| h == '#').count();
    (c.get(i + 1 + hashes) == Some(&'"')).then_some(hashes)
}

/// The module a source file is, from its path relative to `src` (`None` for a file that is not
/// a Rust source).
fn file_module(rel: &str) -> Option<ModPath> {
    let stem = rel.strip_suffix(".rs")?;
    let mut parts: ModPath = stem.split('/').map(str::to_string).collect();
    let last = parts.last()?.as_str();
    if last == "mod" || (parts.len() == 1 && (last == "lib" || last == "main")) {
        parts.pop();
    }
    Some(parts)
}

/// A `use` leaf: the full path it names, the name it brings into scope (`None` for a glob) and
/// its line.
#[derive(Clone, Debug)]
struct UseLeaf {
    path: Vec<String>,
    name: Option<String>,
    line: usize,
}

/// Expands the tree of one `use` declaration (the text between `use` and `;`, as tokens with
/// their lines) into its leaves.
fn expand_use(tokens: &[(String, usize)]) -> Vec<UseLeaf> {
    fn tree(t: &[(String, usize)], at: &mut usize, prefix: &[String], out: &mut Vec<UseLeaf>) {
        let mut path = prefix.to_vec();
        loop {
            let Some((tok, line)) = t.get(*at) else {
                return;
            };
            match tok.as_str() {
                "{" => {
                    *at += 1;
                    while t.get(*at).is_some_and(|(s, _)| s != "}") {
                        tree(t, at, &path, out);
                        if t.get(*at).is_some_and(|(s, _)| s == ",") {
                            *at += 1;
                        }
                    }
                    *at += 1;
                    return;
                }
                "*" => {
                    *at += 1;
                    out.push(UseLeaf {
                        path,
                        name: None,
                        line: *line,
                    });
                    return;
                }
                _ => {
                    path.push(tok.clone());
                    *at += 1;
                    if t.get(*at).is_some_and(|(s, _)| s == "::") {
                        *at += 1;
                        continue;
                    }
                    let mut name = tok.clone();
                    if t.get(*at).is_some_and(|(s, _)| s == "as") {
                        name = t.get(*at + 1).map(|(s, _)| s.clone()).unwrap_or_default();
                        *at += 2;
                    }
                    if path.last().is_some_and(|s| s == "self") {
                        path.pop();
                        if name == "self" {
                            name = path.last().cloned().unwrap_or_default();
                        }
                    }
                    out.push(UseLeaf {
                        path,
                        name: Some(name),
                        line: *line,
                    });
                    return;
                }
            }
        }
    }
    let mut out = Vec::new();
    let mut at = 0;
    tree(tokens, &mut at, &[], &mut out);
    out
}

/// Splits code into identifier, `::` and punctuation tokens with their (1-based) lines.
fn tokens(code: &str, first_line: usize) -> Vec<(String, usize)> {
    let mut out = Vec::new();
    for (k, text) in code.lines().enumerate() {
        let line = first_line + k;
        let c: Vec<char> = text.chars().collect();
        let mut i = 0;
        while i < c.len() {
            if c[i].is_alphanumeric() || c[i] == '_' {
                let start = i;
                while i < c.len() && (c[i].is_alphanumeric() || c[i] == '_') {
                    i += 1;
                }
                out.push((c[start..i].iter().collect(), line));
            } else if c[i] == ':' && c.get(i + 1) == Some(&':') {
                out.push(("::".to_string(), line));
                i += 2;
            } else if c[i].is_whitespace() {
                i += 1;
            } else {
                out.push((c[i].to_string(), line));
                i += 1;
            }
        }
    }
    out
}

/// A path to an item of the crate found in a module, with where it was seen.
#[derive(Clone, Debug)]
struct Reference {
    from: ModPath,
    path: Vec<String>,
    /// Whether it is a `use` path (whose first segment may also name a child module).
    is_use: bool,
    site: Site,
}

/// Everything the checker reads from one crate's sources.
#[derive(Default)]
struct Crate {
    modules: BTreeSet<ModPath>,
    /// The names each module brings into scope with `use`, to follow re-exports.
    imports: BTreeMap<ModPath, Vec<UseLeaf>>,
    references: Vec<Reference>,
}

/// The visibility prefix of an item (`pub`, `pub(crate)`, `pub(in ..)`), removed.
fn without_visibility(s: &str) -> &str {
    let Some(rest) = s.strip_prefix("pub") else {
        return s;
    };
    if let Some(inner) = rest.strip_prefix('(') {
        inner
            .find(')')
            .map_or(s, |end| inner[end + 1..].trim_start())
    } else if rest.starts_with(char::is_whitespace) {
        rest.trim_start()
    } else {
        s
    }
}

/// The name of the module a line declares (`mod name {` or `mod name;`), and whether inline.
fn mod_declaration(trimmed: &str) -> Option<(String, bool)> {
    let rest = without_visibility(trimmed).strip_prefix("mod ")?;
    let name: String = rest
        .chars()
        .take_while(|c| c.is_alphanumeric() || *c == '_')
        .collect();
    let after = rest[name.len()..].trim();
    match after {
        "{" => Some((name, true)),
        ";" => Some((name, false)),
        _ => None,
    }
}

impl Crate {
    /// Reads the sources of one crate: `files` are paths relative to `src` with their text.
    fn read(files: &[(String, String)]) -> Crate {
        let mut krate = Crate::default();
        let mut test_modules: Vec<ModPath> = Vec::new();
        let mut per_file = Vec::new();
        for (rel, text) in files {
            let Some(module) = file_module(rel) else {
                continue;
            };
            krate.modules.insert(module.clone());
            per_file.push((rel.clone(), module, code_only(text)));
        }
        for (rel, file_mod, code) in &per_file {
            let lines: Vec<&str> = code.lines().collect();
            // Inline modules open: (path, indentation of the `mod` line).
            let mut stack: Vec<(ModPath, usize)> = Vec::new();
            let mut cfg_test = false;
            let mut skip_until: Option<String> = None;
            let mut pending_use: Option<(String, usize)> = None;
            for (k, raw) in lines.iter().enumerate() {
                let line_no = k + 1;
                if let Some(end) = &skip_until {
                    if raw.trim_end() == end {
                        skip_until = None;
                    }
                    continue;
                }
                let trimmed = raw.trim();
                let indent = raw.len() - raw.trim_start().len();
                if let Some((_, at)) = stack.last() {
                    if trimmed == "}" && indent == *at {
                        stack.pop();
                        continue;
                    }
                }
                let module = stack.last().map_or(file_mod.clone(), |(m, _)| m.clone());
                if trimmed.starts_with("#[cfg(test)]") {
                    cfg_test = true;
                    continue;
                }
                if let Some((name, inline)) = mod_declaration(trimmed) {
                    let mut child = module.clone();
                    child.push(name);
                    if cfg_test {
                        if inline {
                            skip_until = Some(format!("{}}}", " ".repeat(indent)));
                        } else {
                            test_modules.push(child);
                        }
                    } else if inline {
                        krate.modules.insert(child.clone());
                        stack.push((child, indent));
                    }
                    cfg_test = false;
                    continue;
                }
                if !trimmed.is_empty() && !trimmed.starts_with("#[") {
                    cfg_test = false;
                }
                // `use` declarations, possibly over several lines.
                let mut rest_of_line = *raw;
                if pending_use.is_none() {
                    let item = without_visibility(trimmed);
                    if let Some(tree) = item.strip_prefix("use ") {
                        pending_use = Some((String::new(), line_no));
                        rest_of_line = tree;
                    }
                }
                if let Some((text, first)) = &mut pending_use {
                    text.push_str(rest_of_line);
                    text.push('\n');
                    if let Some(end) = text.find(';') {
                        let tree = tokens(&text[..end], *first);
                        for leaf in expand_use(&tree) {
                            krate
                                .imports
                                .entry(module.clone())
                                .or_default()
                                .push(leaf.clone());
                            krate.references.push(Reference {
                                from: module.clone(),
                                site: Site {
                                    file: rel.clone(),
                                    line: leaf.line,
                                    path: leaf.path.join("::"),
                                },
                                path: leaf.path,
                                is_use: true,
                            });
                        }
                        pending_use = None;
                    }
                    continue;
                }
                // Paths in expressions and types.
                let toks = tokens(raw, line_no);
                let mut i = 0;
                while i < toks.len() {
                    let starts = matches!(toks[i].0.as_str(), "crate" | "super" | "self")
                        && toks.get(i + 1).is_some_and(|(s, _)| s == "::")
                        && (i == 0 || (toks[i - 1].0 != "::" && toks[i - 1].0 != "$"));
                    if !starts {
                        i += 1;
                        continue;
                    }
                    let mut path = vec![toks[i].0.clone()];
                    i += 1;
                    while toks.get(i).is_some_and(|(s, _)| s == "::")
                        && toks.get(i + 1).is_some_and(|(s, _)| {
                            s.chars().all(|c| c.is_alphanumeric() || c == '_')
                        })
                    {
                        path.push(toks[i + 1].0.clone());
                        i += 2;
                    }
                    krate.references.push(Reference {
                        from: module.clone(),
                        site: Site {
                            file: rel.clone(),
                            line: line_no,
                            path: path.join("::"),
                        },
                        path,
                        is_use: false,
                    });
                }
            }
        }
        let in_tests = |m: &ModPath| test_modules.iter().any(|t| m.starts_with(t));
        krate.references.retain(|r| !in_tests(&r.from));
        krate.modules.retain(|m| !in_tests(m));
        krate
    }

    /// The module holding the item `path` names from module `from`, or `None` outside the crate.
    fn resolve(
        &self,
        from: &ModPath,
        path: &[String],
        is_use: bool,
        depth: usize,
    ) -> Option<ModPath> {
        if depth > 16 {
            return None;
        }
        let mut cur: ModPath;
        let mut rest = path;
        match path.first()?.as_str() {
            "crate" => {
                cur = Vec::new();
                rest = &path[1..];
            }
            "super" | "self" => {
                cur = from.clone();
                while let Some(seg) = rest.first() {
                    match seg.as_str() {
                        "super" => {
                            cur.pop()?;
                        }
                        "self" => {}
                        _ => break,
                    }
                    rest = &rest[1..];
                }
            }
            first => {
                let mut child = from.clone();
                child.push(first.to_string());
                if !is_use || !self.modules.contains(&child) {
                    return None;
                }
                cur = from.clone();
            }
        }
        for seg in rest {
            let mut child = cur.clone();
            child.push(seg.clone());
            if self.modules.contains(&child) {
                cur = child;
                continue;
            }
            let reexport = self
                .imports
                .get(&cur)
                .and_then(|leaves| leaves.iter().find(|l| l.name.as_deref() == Some(seg)));
            match reexport {
                Some(leaf) => match self.resolve(&cur, &leaf.path, true, depth + 1) {
                    Some(target) => cur = target,
                    None => break,
                },
                None => break,
            }
        }
        Some(cur)
    }

    /// The circles among the children of every module.
    fn circles(&self) -> Vec<Circle> {
        let mut graphs: BTreeMap<ModPath, Graph> = BTreeMap::new();
        for r in &self.references {
            let Some(to) = self.resolve(&r.from, &r.path, r.is_use, 0) else {
                continue;
            };
            let common = r.from.iter().zip(&to).take_while(|(a, b)| a == b).count();
            if common >= r.from.len() || common >= to.len() {
                continue;
            }
            graphs
                .entry(r.from[..common].to_vec())
                .or_default()
                .entry(r.from[common].clone())
                .or_default()
                .entry(to[common].clone())
                .or_insert_with(|| r.site.clone());
        }
        let mut out = Vec::new();
        for (parent, graph) in &graphs {
            for members in strongly_connected(graph) {
                let edges = shortest_circle(graph, &members);
                let others: Vec<(String, String, Site)> = members
                    .iter()
                    .flat_map(|a| {
                        graph[a]
                            .iter()
                            .filter(|(b, _)| members.contains(b))
                            .map(move |(b, site)| (a.clone(), b.clone(), site.clone()))
                    })
                    .filter(|(a, b, _)| !edges.iter().any(|(x, y, _)| x == a && y == b))
                    .collect();
                let prefix = |m: &str| {
                    let mut p = parent.clone();
                    p.push(m.to_string());
                    p.join("::")
                };
                out.push(Circle {
                    parent: if parent.is_empty() {
                        "crate".to_string()
                    } else {
                        parent.join("::")
                    },
                    members: members.iter().map(|m| prefix(m)).collect(),
                    edges: edges
                        .into_iter()
                        .map(|(a, b, s)| (prefix(&a), prefix(&b), s))
                        .collect(),
                    others: others
                        .into_iter()
                        .map(|(a, b, s)| (prefix(&a), prefix(&b), s))
                        .collect(),
                });
            }
        }
        out
    }
}

/// The strongly connected sets of more than one node (Tarjan's algorithm), each sorted.
fn strongly_connected(graph: &Graph) -> Vec<Vec<String>> {
    struct State<'g> {
        graph: &'g Graph,
        index: BTreeMap<&'g str, usize>,
        low: BTreeMap<&'g str, usize>,
        stack: Vec<&'g str>,
        on_stack: BTreeSet<&'g str>,
        out: Vec<Vec<String>>,
    }
    fn visit<'g>(s: &mut State<'g>, v: &'g str) {
        let n = s.index.len();
        s.index.insert(v, n);
        s.low.insert(v, n);
        s.stack.push(v);
        s.on_stack.insert(v);
        for w in s.graph.get(v).into_iter().flat_map(|e| e.keys()) {
            let w = w.as_str();
            if !s.index.contains_key(w) {
                visit(s, w);
                let lw = s.low[w];
                let lv = s.low.get_mut(v).unwrap();
                *lv = (*lv).min(lw);
            } else if s.on_stack.contains(w) {
                let iw = s.index[w];
                let lv = s.low.get_mut(v).unwrap();
                *lv = (*lv).min(iw);
            }
        }
        if s.low[v] == s.index[v] {
            let mut set = Vec::new();
            while let Some(w) = s.stack.pop() {
                s.on_stack.remove(w);
                set.push(w.to_string());
                if w == v {
                    break;
                }
            }
            if set.len() > 1 {
                set.sort();
                s.out.push(set);
            }
        }
    }
    let mut s = State {
        graph,
        index: BTreeMap::new(),
        low: BTreeMap::new(),
        stack: Vec::new(),
        on_stack: BTreeSet::new(),
        out: Vec::new(),
    };
    for v in graph.keys() {
        if !s.index.contains_key(v.as_str()) {
            visit(&mut s, v);
        }
    }
    s.out
}

/// A shortest circle through the first member of a strongly connected set, as edges.
fn shortest_circle(graph: &Graph, members: &[String]) -> Vec<(String, String, Site)> {
    let start = &members[0];
    let mut came_from: BTreeMap<&str, &str> = BTreeMap::new();
    let mut queue = VecDeque::from([start.as_str()]);
    'search: while let Some(v) = queue.pop_front() {
        for w in graph.get(v).into_iter().flat_map(|e| e.keys()) {
            if !members.contains(w) || came_from.contains_key(w.as_str()) {
                continue;
            }
            came_from.insert(w, v);
            if w == start {
                break 'search;
            }
            queue.push_back(w);
        }
    }
    let mut edges = Vec::new();
    let mut to = start.as_str();
    loop {
        let from = came_from[to];
        edges.push((from.to_string(), to.to_string(), graph[from][to].clone()));
        to = from;
        if to == start {
            break;
        }
    }
    edges.reverse();
    edges
}

/// The workspace root.
fn workspace() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// The `.rs` files under `dir`, as paths relative to it with their text.
fn sources(dir: &Path) -> Vec<(String, String)> {
    fn walk(root: &Path, dir: &Path, out: &mut Vec<(String, String)>) {
        let mut entries: Vec<PathBuf> = std::fs::read_dir(dir)
            .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
            .map(|e| e.unwrap().path())
            .collect();
        entries.sort();
        for path in entries {
            if path.is_dir() {
                walk(root, &path, out);
            } else if path.extension().is_some_and(|e| e == "rs") {
                let rel = path.strip_prefix(root).unwrap();
                let rel: Vec<String> = rel
                    .components()
                    .map(|c| c.as_os_str().to_string_lossy().into_owned())
                    .collect();
                let text = std::fs::read_to_string(&path)
                    .unwrap_or_else(|e| panic!("{}: {e}", path.display()));
                out.push((rel.join("/"), text));
            }
        }
    }
    let mut out = Vec::new();
    walk(dir, dir, &mut out);
    out
}

/// The crates of the workspace by folder name (`crates/<name>/src`), and `dsgs` for the
/// program's own `src`.
fn crate_dirs() -> BTreeMap<String, PathBuf> {
    let root = workspace();
    let mut dirs = BTreeMap::new();
    for entry in std::fs::read_dir(root.join("crates")).unwrap() {
        let path = entry.unwrap().path();
        if path.join("src").is_dir() {
            let name = path.file_name().unwrap().to_string_lossy().into_owned();
            dirs.insert(name, path.join("src"));
        }
    }
    dirs.insert("dsgs".to_string(), root.join("src"));
    dirs
}

/// Panics naming every circle in the given crates.
fn assert_no_circles(names: &[&str]) {
    let dirs = crate_dirs();
    let mut report = String::new();
    for name in names {
        let dir = dirs
            .get(*name)
            .unwrap_or_else(|| panic!("no crate `{name}` in the workspace"));
        let circles = Crate::read(&sources(dir)).circles();
        if !circles.is_empty() {
            report.push_str(&format!("crate `{name}`:\n"));
            for c in circles {
                report.push_str(&c.to_string());
            }
        }
    }
    assert!(
        report.is_empty(),
        "modules that import each other:\n{report}"
    );
}

#[test]
fn no_import_circles_within_a_crate() {
    let dirs = crate_dirs();
    let names: Vec<&str> = dirs.keys().map(String::as_str).collect();
    assert!(names.len() >= 10, "{names:?}");
    assert_no_circles(&names);
}

/// The checker itself, on small made-up crates.
mod checker {
    use super::*;

    fn read(files: &[(&str, &str)]) -> Crate {
        let files: Vec<(String, String)> = files
            .iter()
            .map(|(p, t)| (p.to_string(), t.to_string()))
            .collect();
        Crate::read(&files)
    }

    #[test]
    fn finds_a_circle_through_a_use_group_and_names_each_edge() {
        let krate = read(&[
            ("lib.rs", "mod a;\nmod b;\nmod c;\n"),
            ("a.rs", "//! A.\n\nuse crate::{\n    b::{self, B},\n};\n"),
            ("b.rs", "//! B.\nfn f() -> crate::c::C { todo!() }\n"),
            ("c.rs", "//! C.\n\n\nuse super::a::A as Alias;\n"),
        ]);
        let circles = krate.circles();
        assert_eq!(circles.len(), 1, "{circles:?}");
        let text = circles[0].to_string();
        assert!(text.contains("in `crate`: a -> b -> c -> a"), "{text}");
        assert!(text.contains("a -> b: src/a.rs:4 `crate::b`"), "{text}");
        assert!(text.contains("b -> c: src/b.rs:2 `crate::c::C`"), "{text}");
        assert!(text.contains("c -> a: src/c.rs:4 `super::a::A`"), "{text}");
    }

    #[test]
    fn follows_reexports_and_looks_inside_folders() {
        let krate = read(&[
            ("lib.rs", "mod k;\nmod f;\npub use f::Splats;\n"),
            ("f.rs", "use crate::k::run;\n"),
            ("k/mod.rs", "mod x;\nmod y;\npub(crate) use x::run;\n"),
            ("k/x.rs", "use crate::Splats;\nuse super::y::Y;\n"),
            ("k/y.rs", "pub(crate) fn g() { crate::k::x::run() }\n"),
        ]);
        let text: String = krate.circles().iter().map(|c| c.to_string()).collect();
        assert!(text.contains("in `crate`: f -> k -> f"), "{text}");
        assert!(
            text.contains("k -> f: src/k/x.rs:1 `crate::Splats`"),
            "{text}"
        );
        assert!(text.contains("in `k`: k::x -> k::y -> k::x"), "{text}");
        let krate = read(&[
            ("lib.rs", "mod a;\nmod b;\nmod c;\n"),
            ("a.rs", "use crate::b::B;\nuse crate::c::C;\n"),
            ("b.rs", "use crate::a::A;\n"),
            ("c.rs", "use crate::a::A;\n"),
        ]);
        let text: String = krate.circles().iter().map(|c| c.to_string()).collect();
        assert!(
            text.contains("a -> b -> a (modules in the circle: a, b, c)"),
            "{text}"
        );
        assert!(text.contains("other imports among them:"), "{text}");
        assert!(text.contains("a -> c: src/a.rs:2 `crate::c::C`"), "{text}");
        assert!(text.contains("c -> a: src/c.rs:1 `crate::a::A`"), "{text}");
    }

    #[test]
    fn ignores_tests_comments_strings_and_other_crates() {
        let krate = read(&[
            ("lib.rs", "mod a;\nmod b;\n#[cfg(test)]\nmod t;\n"),
            ("a.rs", "use crate::b::B;\n"),
            (
                "b.rs",
                "// crate::a::A\nconst Q: char = '\\'';\n/// [`crate::a`]\nconst S: &str = \"crate::a::A\";\n\
                 const R: &str = r#\"crate::a\"#;\nuse other::a::A;\nfn f<'a>(x: &'a u8) -> char { 'x' }\n\
                 #[cfg(test)]\nmod tests {\n    use crate::a::A;\n    fn g() {\n    }\n}\n\
                 /* crate::a::A /* nested */ crate::a */\n",
            ),
            ("t.rs", "use crate::a::A;\n"),
        ]);
        assert!(krate.circles().is_empty());
        let mut with_b = read(&[
            ("lib.rs", "mod a;\nmod b;\n"),
            ("a.rs", "use crate::b::B;\n"),
            (
                "b.rs",
                "#[cfg(test)]\nmod tests {\n}\nfn f() { crate::a::g() }\n",
            ),
        ]);
        assert_eq!(with_b.circles().len(), 1);
        with_b.references.retain(|r| r.site.file != "b.rs");
        assert!(with_b.circles().is_empty());
    }
}
