//! The source tree keeps the layout `docs/architecture.md` draws: every `crate::` path and every
//! use of a child module in `src/` (comments aside) is an import edge between modules; imports
//! only flow down the layers below (a module uses its own layer and those above it), and no
//! module imports another that imports it back, directly or through others.
use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;

/// Top-level modules by layer, lowest first.
const LAYERS: [&[&str]; 12] = [
    &["math", "util", "limits"],
    &["gpu"],
    &["model"],
    &["formats", "dataset"],
    &["render"],
    &["train"],
    &["segment", "register"],
    &["instancing"],
    &["discover"],
    &["bench"],
    &["pipeline"],
    &["player"],
];

fn layer(module: &str) -> Option<usize> {
    let top = module.split("::").next().unwrap_or_default();
    LAYERS.iter().position(|l| l.contains(&top))
}

/// Module path → source text without comments, for every library file.
fn modules() -> BTreeMap<String, String> {
    fn walk(dir: &Path, out: &mut Vec<std::path::PathBuf>) {
        for e in std::fs::read_dir(dir).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                walk(&p, out);
            } else if p.extension().is_some_and(|x| x == "rs") {
                out.push(p);
            }
        }
    }
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut files = Vec::new();
    walk(&src, &mut files);
    let mut mods = BTreeMap::new();
    for f in files {
        let rel = f.strip_prefix(&src).unwrap().with_extension("");
        let mut parts: Vec<String> = rel.iter().map(|c| c.to_string_lossy().into_owned()).collect();
        if parts.last().is_some_and(|p| p == "mod") {
            parts.pop();
        }
        let name = parts.join("::");
        if ["lib", "main", "cli"].contains(&name.as_str()) {
            continue; // the crate root and the binary sit above every layer
        }
        let text = std::fs::read_to_string(&f).unwrap();
        let code: String = text
            .lines()
            .filter(|l| !l.trim_start().starts_with("//"))
            .map(|l| l.split(" // ").next().unwrap_or_default())
            .collect::<Vec<_>>()
            .join("\n");
        mods.insert(name, code);
    }
    mods
}

/// Import edges: module → the modules it names.
fn edges(mods: &BTreeMap<String, String>) -> BTreeMap<String, BTreeSet<String>> {
    let ident = |c: char| c.is_ascii_alphanumeric() || c == '_';
    let mut edges: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
    for (m, code) in mods {
        let e = edges.entry(m.clone()).or_default();
        for (at, _) in code.match_indices("crate::") {
            let path: String = code[at + 7..].chars().take_while(|&c| ident(c) || c == ':').collect();
            let parts: Vec<&str> = path.split("::").filter(|p| !p.is_empty()).collect();
            if let Some(target) = (1..=parts.len()).rev().map(|k| parts[..k].join("::")).find(|c| mods.contains_key(c))
            {
                if &target != m {
                    e.insert(target);
                }
            }
        }
        // Children named without `crate::` (`child::item`, `use child::…`).
        for line in code.lines() {
            let t = line.trim_start();
            if let Some(child) = t.strip_prefix("pub mod ").or_else(|| t.strip_prefix("mod ")) {
                let child = child.trim_end_matches(';');
                if child.chars().all(ident) {
                    let full = if m.is_empty() { child.to_string() } else { format!("{m}::{child}") };
                    let used = code
                        .match_indices(&format!("{child}::"))
                        .any(|(i, _)| i == 0 || !code[..i].ends_with(|c: char| ident(c) || c == ':'));
                    if used && mods.contains_key(&full) {
                        e.insert(full);
                    }
                }
            }
        }
    }
    edges
}

#[test]
fn imports_flow_down_the_layers() {
    let mods = modules();
    assert!(mods.len() > 30, "found {} modules", mods.len());
    for m in mods.keys() {
        assert!(layer(m).is_some(), "{m} is in no layer of this test (and of docs/architecture.md)");
    }
    let mut upward = Vec::new();
    for (a, targets) in edges(&mods) {
        for b in targets {
            if layer(&b) > layer(&a) {
                upward.push(format!("{a} -> {b}"));
            }
        }
    }
    assert!(upward.is_empty(), "imports running up the layers: {upward:#?}");
}

#[test]
fn no_module_imports_one_that_imports_it_back() {
    let e = edges(&modules());
    // Depth-first search for a cycle; reports one.
    fn visit(
        m: &str,
        e: &BTreeMap<String, BTreeSet<String>>,
        state: &mut BTreeMap<String, u8>,
        stack: &mut Vec<String>,
    ) -> Option<Vec<String>> {
        state.insert(m.to_string(), 1);
        stack.push(m.to_string());
        for n in e.get(m).into_iter().flatten() {
            match state.get(n.as_str()) {
                Some(1) => {
                    let from = stack.iter().position(|s| s == n).unwrap();
                    let mut cycle = stack[from..].to_vec();
                    cycle.push(n.clone());
                    return Some(cycle);
                }
                Some(_) => {}
                None => {
                    if let Some(c) = visit(n, e, state, stack) {
                        return Some(c);
                    }
                }
            }
        }
        stack.pop();
        state.insert(m.to_string(), 2);
        None
    }
    let mut state = BTreeMap::new();
    for m in e.keys() {
        if !state.contains_key(m.as_str()) {
            let cycle = visit(m, &e, &mut state, &mut Vec::new());
            assert!(cycle.is_none(), "import loop: {}", cycle.unwrap().join(" -> "));
        }
    }
}

#[test]
fn the_binary_holds_no_command_logic() {
    // main.rs dispatches and prints; cli.rs holds the clap types. Neither talks to the device,
    // reads files or builds reports itself.
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    for f in ["main.rs", "cli.rs"] {
        let text = std::fs::read_to_string(root.join(f)).unwrap();
        for banned in ["Gpu::new", "Kernels::new", "Rasterizer::new", "std::fs::", "serde_json::json!"] {
            assert!(!text.contains(banned), "src/{f} uses {banned}: that work belongs in the library");
        }
    }
}
