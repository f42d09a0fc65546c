//! No import cycle between the files of any crate.
//!
//! Each source file is a module; an edge `a → b` means file `a` names an item of file `b`
//! through `crate::…`, `super::…` or `self::…` (in `use` declarations or in paths). A path to an
//! item that a module only re-exports (`pub use x::Item`) is followed to the file that defines
//! it. Inline `#[cfg(test)]` modules are left out: they sit below their file and may use it.
//! The test fails with every cycle it finds, file by file.

use std::collections::{BTreeMap, BTreeSet};
use std::fs;
use std::path::{Path, PathBuf};

/// One crate's module tree: module path (segments) → file, and each file's text.
struct Crate {
    name: String,
    modules: BTreeMap<Vec<String>, PathBuf>,
    text: BTreeMap<Vec<String>, String>,
}

fn workspace_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .unwrap()
        .to_path_buf()
}

/// Crate folders named in the workspace manifest's `members`.
fn members(root: &Path) -> Vec<PathBuf> {
    let manifest = fs::read_to_string(root.join("Cargo.toml")).unwrap();
    let start = manifest.find("members").expect("workspace members");
    let open = start + manifest[start..].find('[').unwrap();
    let close = open + manifest[open..].find(']').unwrap();
    manifest[open + 1..close]
        .lines()
        .map(|l| l.split('#').next().unwrap().trim().trim_end_matches(','))
        .filter(|l| !l.is_empty())
        .map(|l| root.join(l.trim_matches('"')))
        .collect()
}

/// Removes comments and string/char literal contents, and cuts inline test modules.
fn code_of(src: &str) -> String {
    let mut out = String::with_capacity(src.len());
    let b = src.as_bytes();
    let mut i = 0;
    while i < b.len() {
        if b[i] == b'/' && b.get(i + 1) == Some(&b'/') {
            while i < b.len() && b[i] != b'\n' {
                i += 1;
            }
        } else if b[i] == b'/' && b.get(i + 1) == Some(&b'*') {
            i += 2;
            while i + 1 < b.len() && !(b[i] == b'*' && b[i + 1] == b'/') {
                i += 1;
            }
            i += 2;
        } else if b[i] == b'\'' && (b.get(i + 2) == Some(&b'\'') || b.get(i + 1) == Some(&b'\\')) {
            // A char literal (not a lifetime): skip it whole, quotes included.
            i += 2;
            while i < b.len() && b[i] != b'\'' {
                i += 1;
            }
            i += 1;
            out.push(' ');
        } else if b[i] == b'r'
            && (b.get(i + 1) == Some(&b'"') || b.get(i + 1) == Some(&b'#'))
            && (i == 0 || !(b[i - 1].is_ascii_alphanumeric() || b[i - 1] == b'_'))
        {
            // A raw string `r#"…"#`: skip to the quote followed by as many hashes.
            let mut j = i + 1;
            while b.get(j) == Some(&b'#') {
                j += 1;
            }
            if b.get(j) != Some(&b'"') {
                out.push(b[i] as char);
                i += 1;
                continue;
            }
            let hashes = j - i - 1;
            let close: Vec<u8> = std::iter::once(b'"')
                .chain(std::iter::repeat_n(b'#', hashes))
                .collect();
            j += 1;
            while j < b.len() && !b[j..].starts_with(&close) {
                j += 1;
            }
            i = j + close.len();
            out.push(' ');
        } else if b[i] == b'"' {
            out.push(' ');
            i += 1;
            while i < b.len() && b[i] != b'"' {
                if b[i] == b'\\' {
                    i += 1;
                }
                i += 1;
            }
            i += 1;
        } else {
            out.push(b[i] as char);
            i += 1;
        }
    }
    // An inline `#[cfg(test)] mod name { … }` is the file's last item by convention here.
    let mut cut = out.len();
    let mut from = 0;
    while let Some(p) = out[from..].find("#[cfg(test)]") {
        let at = from + p;
        let rest = out[at + 12..].trim_start();
        if rest.starts_with("mod ") && rest[..rest.find(['{', ';']).unwrap_or(0)].len() < 40 {
            let brace = rest.find(['{', ';']).unwrap_or(0);
            if rest.as_bytes().get(brace) == Some(&b'{') {
                cut = at;
                break;
            }
        }
        from = at + 12;
    }
    out.truncate(cut);
    out
}

fn load_crate(dir: &Path) -> Option<Crate> {
    let src = dir.join("src");
    let root = [src.join("lib.rs"), src.join("main.rs")]
        .into_iter()
        .find(|p| p.exists())?;
    let mut c = Crate {
        name: dir.file_name().unwrap().to_string_lossy().into_owned(),
        modules: BTreeMap::new(),
        text: BTreeMap::new(),
    };
    let mut stack = vec![(Vec::<String>::new(), root)];
    while let Some((path, file)) = stack.pop() {
        let code = code_of(&fs::read_to_string(&file).unwrap());
        // `mod name;` declarations (file modules) below this one.
        let base = if path.is_empty() || file.file_name().is_some_and(|n| n == "mod.rs") {
            file.parent().unwrap().to_path_buf()
        } else {
            file.with_extension("")
        };
        for stmt in code.split(';') {
            let words: Vec<&str> = stmt.split_whitespace().collect();
            let Some(k) = words.iter().position(|w| *w == "mod") else {
                continue;
            };
            if k + 2 != words.len() || words[..k].iter().any(|w| w.contains('{')) {
                continue;
            }
            let name = words[k + 1].to_string();
            let mut child = path.clone();
            child.push(name.clone());
            let f = [
                base.join(format!("{name}.rs")),
                base.join(&name).join("mod.rs"),
            ]
            .into_iter()
            .find(|p| p.exists());
            if let Some(f) = f {
                stack.push((child, f));
            }
        }
        c.modules.insert(path.clone(), file);
        c.text.insert(path, code);
    }
    Some(c)
}

/// Every module-relative path a file names: `use` trees expanded, plus inline paths.
fn paths_in(code: &str) -> Vec<Vec<String>> {
    fn expand(prefix: &str, tree: &str, out: &mut Vec<String>) {
        let tree = tree.trim();
        if let Some(open) = tree.find('{') {
            let head = tree[..open].trim().trim_end_matches("::");
            let inner = &tree[open + 1..tree.rfind('}').unwrap_or(tree.len())];
            let mut depth = 0;
            let mut start = 0;
            let full = join(prefix, head);
            for (i, ch) in inner.char_indices() {
                match ch {
                    '{' => depth += 1,
                    '}' => depth -= 1,
                    ',' if depth == 0 => {
                        expand(&full, &inner[start..i], out);
                        start = i + 1;
                    }
                    _ => {}
                }
            }
            expand(&full, &inner[start..], out);
        } else if !tree.is_empty() {
            let item = tree.split(" as ").next().unwrap().trim();
            out.push(join(prefix, item));
        }
    }
    fn join(a: &str, b: &str) -> String {
        match (a.is_empty(), b.is_empty()) {
            (true, _) => b.to_string(),
            (_, true) => a.to_string(),
            _ => format!("{a}::{b}"),
        }
    }
    let mut raw = Vec::new();
    for stmt in code.split(';') {
        if let Some(p) = stmt.find("use ") {
            let before = stmt[..p].trim_end();
            let is_decl = before.is_empty()
                || before.ends_with("pub")
                || before.ends_with(')')
                || before.ends_with('}')
                || before.ends_with(']');
            if is_decl {
                expand("", &stmt[p + 4..], &mut raw);
            }
        }
    }
    // Inline paths such as `crate::manifest::MapDir::open(…)`.
    let bytes = code.as_bytes();
    for key in ["crate::", "super::", "self::"] {
        let mut from = 0;
        while let Some(p) = code[from..].find(key) {
            let at = from + p;
            let ok_before = at == 0
                || !(bytes[at - 1].is_ascii_alphanumeric()
                    || bytes[at - 1] == b'_'
                    || bytes[at - 1] == b':');
            let mut end = at;
            while end < bytes.len()
                && (bytes[end].is_ascii_alphanumeric() || bytes[end] == b'_' || bytes[end] == b':')
            {
                end += 1;
            }
            if ok_before {
                raw.push(code[at..end].trim_end_matches(':').to_string());
            }
            from = at + key.len();
        }
    }
    raw.into_iter()
        .map(|p| {
            p.split("::")
                .map(|s| s.trim().to_string())
                .filter(|s| !s.is_empty())
                .collect()
        })
        .collect()
}

/// The file a path (absolute module segments + item) lands in, following re-exports.
fn resolve(c: &Crate, path: &[String], depth: usize) -> Option<Vec<String>> {
    let mut k = path.len();
    while k > 0 && !c.modules.contains_key(&path[..k]) {
        k -= 1;
    }
    let module = path[..k].to_vec();
    let Some(item) = path.get(k) else {
        return Some(module);
    };
    if depth < 8 {
        // `pub use x::{…, Item, …}` in that module: go where `Item` is defined.
        for p in paths_in(&reexports(&c.text[&module])) {
            if p.last() == Some(item)
                && let Some(abs) = absolute(&module, &p)
                && abs != path
            {
                return resolve(c, &abs, depth + 1);
            }
        }
    }
    Some(module)
}

/// The `pub use` declarations of a file, as code.
fn reexports(code: &str) -> String {
    code.split(';')
        .filter(|s| {
            let t = s.trim_start();
            t.starts_with("pub use ") || t.starts_with("pub(crate) use ")
        })
        .map(|s| format!("{s};"))
        .collect()
}

/// `crate::`/`super::`/`self::`/sibling paths made absolute from module `from`.
fn absolute(from: &[String], p: &[String]) -> Option<Vec<String>> {
    let mut base: Vec<String>;
    let mut rest = p;
    match p.first().map(String::as_str) {
        Some("crate") => {
            base = Vec::new();
            rest = &p[1..];
        }
        Some("self") => {
            base = from.to_vec();
            rest = &p[1..];
        }
        Some("super") => {
            base = from.to_vec();
            while rest.first().map(String::as_str) == Some("super") {
                base.pop()?;
                rest = &rest[1..];
            }
        }
        _ => {
            // A 2018-style relative path (`use child::Item` in a parent module).
            base = from.to_vec();
        }
    }
    base.extend(rest.iter().cloned());
    Some(base)
}

fn cycles(c: &Crate) -> Vec<Vec<String>> {
    let ids: Vec<&Vec<String>> = c.modules.keys().collect();
    let index: BTreeMap<&Vec<String>, usize> =
        ids.iter().enumerate().map(|(i, m)| (*m, i)).collect();
    let mut edges: Vec<BTreeSet<usize>> = vec![BTreeSet::new(); ids.len()];
    for (m, code) in &c.text {
        for p in paths_in(code) {
            let relative = !matches!(
                p.first().map(String::as_str),
                Some("crate" | "self" | "super")
            );
            if relative
                && !c
                    .modules
                    .contains_key(&[m.clone(), vec![p[0].clone()]].concat())
            {
                continue; // an external crate or a std path
            }
            let Some(abs) = absolute(m, &p) else { continue };
            if let Some(target) = resolve(c, &abs, 0)
                && &target != m
                && !target.starts_with(m)
            {
                edges[index[m]].insert(index[&target]);
            }
        }
    }
    // Tarjan's strongly connected components.
    struct T<'a> {
        edges: &'a [BTreeSet<usize>],
        index: Vec<Option<usize>>,
        low: Vec<usize>,
        on: Vec<bool>,
        stack: Vec<usize>,
        next: usize,
        out: Vec<Vec<usize>>,
    }
    fn visit(t: &mut T, v: usize) {
        t.index[v] = Some(t.next);
        t.low[v] = t.next;
        t.next += 1;
        t.stack.push(v);
        t.on[v] = true;
        for &w in t.edges[v].clone().iter() {
            match t.index[w] {
                None => {
                    visit(t, w);
                    t.low[v] = t.low[v].min(t.low[w]);
                }
                Some(iw) if t.on[w] => t.low[v] = t.low[v].min(iw),
                _ => {}
            }
        }
        if Some(t.low[v]) == t.index[v] {
            let mut comp = Vec::new();
            loop {
                let w = t.stack.pop().unwrap();
                t.on[w] = false;
                comp.push(w);
                if w == v {
                    break;
                }
            }
            if comp.len() > 1 {
                t.out.push(comp);
            }
        }
    }
    let n = ids.len();
    let mut t = T {
        edges: &edges,
        index: vec![None; n],
        low: vec![0; n],
        on: vec![false; n],
        stack: Vec::new(),
        next: 0,
        out: Vec::new(),
    };
    for v in 0..n {
        if t.index[v].is_none() {
            visit(&mut t, v);
        }
    }
    t.out
        .into_iter()
        .map(|comp| {
            comp.into_iter()
                .map(|i| {
                    let f = &c.modules[ids[i]];
                    f.strip_prefix(workspace_root())
                        .unwrap_or(f)
                        .display()
                        .to_string()
                })
                .collect()
        })
        .collect()
}

#[test]
fn no_crate_has_an_import_cycle_between_its_files() {
    let root = workspace_root();
    let mut found = Vec::new();
    let mut files = 0;
    for dir in members(&root) {
        let Some(c) = load_crate(&dir) else { continue };
        files += c.modules.len();
        for cycle in cycles(&c) {
            found.push(format!("{}: {}", c.name, cycle.join(" ↔ ")));
        }
    }
    assert!(
        files > 50,
        "only {files} source files found under {}",
        root.display()
    );
    assert!(found.is_empty(), "import cycles:\n{}", found.join("\n"));
}

#[test]
fn the_checker_sees_a_planted_cycle() {
    let dir = tempfile::tempdir().unwrap();
    let src = dir.path().join("src");
    fs::create_dir_all(&src).unwrap();
    fs::write(
        src.join("lib.rs"),
        "mod a;\nmod b;\nmod c;\npub use c::C;\n",
    )
    .unwrap();
    fs::write(src.join("a.rs"), "use crate::b::B;\npub struct A;\n").unwrap();
    fs::write(
        src.join("b.rs"),
        "pub struct B;\nfn f() { let _ = super::a::A; }\n",
    )
    .unwrap();
    fs::write(
        src.join("c.rs"),
        "use crate::C as _;\npub struct C;\n#[cfg(test)]\nmod tests {\n    use super::super::a::A;\n}\n",
    )
    .unwrap();
    let c = load_crate(dir.path()).unwrap();
    let found = cycles(&c);
    assert_eq!(found.len(), 1, "{found:?}");
    let mut names: Vec<String> = found[0]
        .iter()
        .map(|f| {
            Path::new(f)
                .file_name()
                .unwrap()
                .to_string_lossy()
                .into_owned()
        })
        .collect();
    names.sort();
    assert_eq!(names, ["a.rs", "b.rs"]);
}
