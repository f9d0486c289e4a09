//! Fuzz target: a 3DGS PLY that reads, written to every format `convert` writes and read back (fuzz/inputs.rs). Run from the repository root:
//! `cargo +nightly fuzz run convert_any fuzz/seeds/convert_any`.
#![no_main]
#[path = "../inputs.rs"]
mod inputs;

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let _ = inputs::run("convert_any", data);
});
