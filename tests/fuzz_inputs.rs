//! The fuzz targets' inputs kept in the repository, run through the same code as the targets
//! (`fuzz/inputs.rs`): every seed (`fuzz/seeds/<target>/`, small valid files) is accepted, and
//! every regression input (`fuzz/regressions/<target>/`: inputs that once crashed, hung or were
//! misread) is refused with an error, without a panic.
#[path = "../fuzz/inputs.rs"]
mod inputs;

use std::path::Path;

fn files(dir: &Path) -> Vec<std::path::PathBuf> {
    let mut v: Vec<_> = std::fs::read_dir(dir).map_or(Vec::new(), |d| d.map(|e| e.unwrap().path()).collect());
    v.sort();
    v
}

#[test]
fn every_seed_is_accepted() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("fuzz/seeds");
    for (target, what) in inputs::TARGETS {
        let seeds = files(&root.join(target));
        assert!(!seeds.is_empty(), "fuzz/seeds/{target} ({what}) has no seed");
        for f in seeds {
            let data = std::fs::read(&f).unwrap();
            if let Err(e) = inputs::run(target, &data) {
                panic!("{}: refused by {target}: {e:#}", f.display());
            }
        }
    }
}

#[test]
fn every_regression_input_is_refused() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("fuzz/regressions");
    let mut n = 0;
    for (target, _) in inputs::TARGETS {
        for f in files(&root.join(target)) {
            let data = std::fs::read(&f).unwrap();
            assert!(inputs::run(target, &data).is_err(), "{}: accepted by {target}", f.display());
            n += 1;
        }
    }
    for dir in files(&root) {
        let name = dir.file_name().unwrap().to_string_lossy().into_owned();
        assert!(inputs::TARGETS.iter().any(|(t, _)| *t == name), "fuzz/regressions/{name}: no such target");
    }
    eprintln!("{n} regression inputs refused");
}
