//! The documentation stays true: the README stays short, every relative link of the README,
//! BENCHMARKS and docs/ leads to a file (and heading) that exists, every flag the binary accepts
//! is in docs/usage.md, and no source file outgrows its room.
use std::collections::BTreeSet;
use std::fs;
use std::path::{Path, PathBuf};
use std::process::Command;

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

fn pages() -> Vec<PathBuf> {
    let mut pages = vec![root().join("README.md"), root().join("BENCHMARKS.md")];
    let mut docs: Vec<PathBuf> = fs::read_dir(root().join("docs"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "md"))
        .collect();
    docs.sort();
    pages.extend(docs);
    pages
}

/// GitHub's anchor of a heading: lower case, punctuation dropped, spaces to hyphens.
fn slug(heading: &str) -> String {
    heading
        .trim()
        .to_lowercase()
        .chars()
        .filter_map(|c| match c {
            ' ' => Some('-'),
            c if c.is_alphanumeric() || c == '-' || c == '_' => Some(c),
            _ => None,
        })
        .collect()
}

/// The lines of a page outside its code blocks.
fn prose_lines(text: &str) -> impl Iterator<Item = &str> {
    let mut in_code = false;
    text.lines().filter(move |line| {
        if line.starts_with("```") {
            in_code = !in_code;
            return false;
        }
        !in_code
    })
}

fn anchors(text: &str) -> BTreeSet<String> {
    prose_lines(text).filter(|l| l.starts_with('#')).map(|l| slug(l.trim_start_matches('#'))).collect()
}

/// Markdown links `[text](target)` outside code blocks.
fn links(text: &str) -> Vec<String> {
    let mut out = Vec::new();
    for line in prose_lines(text) {
        let mut rest = line;
        while let Some(i) = rest.find("](") {
            let tail = &rest[i + 2..];
            let Some(end) = tail.find(')') else { break };
            out.push(tail[..end].to_string());
            rest = &tail[end..];
        }
    }
    out
}

#[test]
fn the_readme_is_read_in_five_minutes() {
    let readme = fs::read_to_string(root().join("README.md")).unwrap();
    let lines = readme.lines().count();
    assert!(lines <= 200, "README.md has {lines} lines; the manual (docs/) takes the rest");
    for command in ["bash tools/demo.sh", "bash tools/test.sh"] {
        assert!(readme.contains(command), "README.md lacks the set-up command {command}");
    }
}

#[test]
fn every_page_starts_with_what_it_is_for_and_its_links_resolve() {
    let mut dead = Vec::new();
    for page in pages() {
        let text = fs::read_to_string(&page).unwrap();
        assert!(text.starts_with("# "), "{} does not start with its title", page.display());
        for link in links(&text) {
            if link.contains("://") || link.starts_with("mailto:") {
                continue;
            }
            let (file, anchor) = match link.split_once('#') {
                Some((f, a)) => (f, Some(a)),
                None => (link.as_str(), None),
            };
            let target = if file.is_empty() { page.clone() } else { page.parent().unwrap().join(file) };
            if !target.exists() {
                dead.push(format!("{}: {link} (no such file)", page.display()));
                continue;
            }
            if let Some(anchor) = anchor {
                let text = fs::read_to_string(&target).unwrap_or_default();
                if !anchors(&text).contains(anchor) {
                    dead.push(format!("{}: {link} (no such heading)", page.display()));
                }
            }
        }
    }
    assert!(dead.is_empty(), "dead links:\n{}", dead.join("\n"));
}

fn help(args: &[&str]) -> String {
    let out = Command::new(env!("CARGO_BIN_EXE_instgs-vk")).args(args).arg("--help").output().unwrap();
    assert!(out.status.success(), "instgs-vk {args:?} --help failed");
    String::from_utf8(out.stdout).unwrap()
}

#[test]
fn every_flag_is_in_the_manual() {
    let usage = fs::read_to_string(root().join("docs/usage.md")).unwrap();
    let top = help(&[]);
    let commands: Vec<String> = top
        .lines()
        .skip_while(|l| !l.starts_with("Commands:"))
        .skip(1)
        .take_while(|l| l.starts_with("  "))
        .filter_map(|l| l.split_whitespace().next().map(str::to_string))
        .filter(|c| c != "help")
        .collect();
    assert!(commands.len() >= 10, "commands not found in the help: {commands:?}");
    let mut missing = Vec::new();
    for command in &commands {
        assert!(usage.contains(command.as_str()), "docs/usage.md lacks the command {command}");
        let text = help(&[command.as_str()]);
        for word in text.split(|c: char| !(c.is_alphanumeric() || c == '-')) {
            let Some(flag) = word.strip_prefix("--") else { continue };
            if flag.is_empty() || flag == "help" || !flag.starts_with(|c: char| c.is_ascii_lowercase()) {
                continue;
            }
            if !usage.contains(&format!("--{flag}")) {
                missing.push(format!("{command} --{flag}"));
            }
        }
    }
    missing.sort();
    missing.dedup();
    assert!(missing.is_empty(), "flags missing from docs/usage.md:\n{}", missing.join("\n"));
}

fn sources(dir: &Path, out: &mut Vec<PathBuf>) {
    for entry in fs::read_dir(dir).unwrap() {
        let path = entry.unwrap().path();
        if path.is_dir() {
            sources(&path, out);
        } else if path.extension().is_some_and(|e| e == "rs") {
            out.push(path);
        }
    }
}

#[test]
fn source_files_fit_their_room() {
    const MAX_LINES: usize = 700;
    let mut files = Vec::new();
    sources(&root().join("src"), &mut files);
    let mut large: Vec<String> = files
        .iter()
        .filter_map(|f| {
            let n = fs::read_to_string(f).unwrap().lines().count();
            (n > MAX_LINES).then(|| format!("{} ({n} lines)", f.strip_prefix(root()).unwrap().display()))
        })
        .collect();
    large.sort();
    assert!(large.is_empty(), "source files above {MAX_LINES} lines:\n{}", large.join("\n"));
}

/// The functions of `text` with their first line (1-based) and length in lines: a line that
/// declares a `fn` with a body, to the line that closes it at the same indentation (rustfmt's
/// layout, which the sources keep).
fn function_lengths(text: &str) -> Vec<(usize, usize, String)> {
    let lines: Vec<&str> = text.lines().collect();
    let mut out = Vec::new();
    for (i, line) in lines.iter().enumerate() {
        let body = line.trim_start();
        let indent = &line[..line.len() - body.len()];
        let decl = ["pub(crate) ", "pub(super) ", "pub ", "const ", "unsafe ", "async ", "extern \"C\" "]
            .iter()
            .fold(body, |b, p| b.strip_prefix(p).unwrap_or(b));
        if !decl.starts_with("fn ") {
            continue;
        }
        let Some(open) = (i..lines.len()).find(|&j| lines[j].ends_with('{') || lines[j].ends_with(';')) else {
            continue;
        };
        if lines[open].ends_with(';') {
            continue;
        }
        let close = format!("{indent}}}");
        if let Some(end) = (open + 1..lines.len()).find(|&j| lines[j] == close) {
            let name = decl[3..].split(['(', '<']).next().unwrap_or("").to_string();
            out.push((i + 1, end - i + 1, name));
        }
    }
    out
}

#[test]
fn functions_fit_their_room() {
    const MAX_LINES: usize = 150;
    let mut files = Vec::new();
    sources(&root().join("src"), &mut files);
    let mut long: Vec<String> = Vec::new();
    for f in &files {
        for (line, n, name) in function_lengths(&fs::read_to_string(f).unwrap()) {
            if n > MAX_LINES {
                long.push(format!("{}:{line} {name} ({n} lines)", f.strip_prefix(root()).unwrap().display()));
            }
        }
    }
    long.sort();
    assert!(long.is_empty(), "functions above {MAX_LINES} lines:\n{}", long.join("\n"));
    // The measure itself: this file's own test functions are found with their lengths.
    let own = function_lengths(&fs::read_to_string(root().join("tests/docs.rs")).unwrap());
    assert!(own.iter().any(|(_, n, name)| name == "functions_fit_their_room" && *n > 10), "{own:?}");
}
