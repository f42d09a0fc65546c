//! ARCHITECTURE.md shows the stage traits as they are: every trait block in its "stage traits"
//! section names its source file and must equal that trait's definition there (doc comments
//! left out).

use std::fs;
use std::path::{Path, PathBuf};

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .unwrap()
        .to_path_buf()
}

/// `(file, trait text)` for every block of the section: a `// path: what` line, then the trait.
fn documented_traits(doc: &str) -> Vec<(String, String)> {
    let start = doc
        .find("## The stage traits")
        .expect("a stage traits section");
    let code = &doc[start..];
    let open = code.find("```rust\n").expect("a rust block") + "```rust\n".len();
    let close = open + code[open..].find("```").expect("the block ends");
    let mut out: Vec<(String, String)> = Vec::new();
    for line in code[open..close].lines() {
        if let Some(header) = line.strip_prefix("// ") {
            let file = header.split(':').next().unwrap().trim().to_string();
            out.push((file, String::new()));
        } else if let Some((_, text)) = out.last_mut() {
            text.push_str(line);
            text.push('\n');
        }
    }
    out.into_iter()
        .map(|(f, t)| (f, t.trim_end().to_string()))
        .collect()
}

/// The definition of the trait named in `block`'s first line, from `source`, without doc
/// comments.
fn source_trait(source: &str, block: &str) -> Option<String> {
    let first = block.lines().next()?;
    let name = first
        .strip_prefix("pub trait ")?
        .split(|c: char| !(c.is_alphanumeric() || c == '_'))
        .next()?;
    let lines: Vec<&str> = source.lines().collect();
    let at = lines.iter().position(|l| {
        l.strip_prefix("pub trait ").is_some_and(|r| {
            r.starts_with(name) && !r[name.len()..].starts_with(char::is_alphanumeric)
        })
    })?;
    let end = at + lines[at..].iter().position(|l| *l == "}")?;
    Some(
        lines[at..=end]
            .iter()
            .filter(|l| !l.trim_start().starts_with("///"))
            .map(|l| l.trim_end())
            .collect::<Vec<_>>()
            .join("\n"),
    )
}

#[test]
fn the_documented_traits_match_the_source() {
    let root = root();
    let doc = fs::read_to_string(root.join("ARCHITECTURE.md")).unwrap();
    let blocks = documented_traits(&doc);
    assert!(
        blocks.len() >= 8,
        "only {} trait blocks documented",
        blocks.len()
    );
    let mut wrong = Vec::new();
    for (file, block) in &blocks {
        let source = fs::read_to_string(root.join(file))
            .unwrap_or_else(|e| panic!("ARCHITECTURE.md names {file}: {e}"));
        match source_trait(&source, block) {
            Some(actual) if actual == *block => {}
            Some(actual) => wrong.push(format!("{file}: documented\n{block}\nactual\n{actual}")),
            None => wrong.push(format!("{file}: no trait for the block\n{block}")),
        }
    }
    assert!(
        wrong.is_empty(),
        "ARCHITECTURE.md is out of date:\n{}",
        wrong.join("\n\n")
    );
}

#[test]
fn a_changed_signature_is_caught() {
    let source = "/// Doc.\npub trait T: Send {\n    /// One.\n    fn a(&self) -> usize;\n}\n";
    let block = "pub trait T: Send {\n    fn a(&self) -> usize;\n}";
    assert_eq!(source_trait(source, block).as_deref(), Some(block));
    let changed = "pub trait T: Send {\n    fn a(&self) -> u32;\n}";
    assert_ne!(source_trait(source, changed).as_deref(), Some(changed));
    assert_eq!(source_trait(source, "pub trait U {\n}"), None);
}
