//! Fuzz target: COLMAP cameras/images/points3D, .bin and .txt, on arbitrary bytes (fuzz/inputs.rs). Run from the repository root:
//! `cargo +nightly fuzz run colmap_parse fuzz/seeds/colmap_parse`.
#![no_main]
#[path = "../inputs.rs"]
mod inputs;

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let _ = inputs::run("colmap_parse", data);
});
