//! Fuzz target: 3DGS PLY, plain and SuperSplat compressed, on arbitrary bytes (fuzz/inputs.rs). Run from the repository root:
//! `cargo +nightly fuzz run ply_parse fuzz/seeds/ply_parse`.
#![no_main]
#[path = "../inputs.rs"]
mod inputs;

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let _ = inputs::run("ply_parse", data);
});
