//! Fuzz target: .instgs scene, on arbitrary bytes (fuzz/inputs.rs). Run from the repository root:
//! `cargo +nightly fuzz run instgs_parse fuzz/seeds/instgs_parse`.
#![no_main]
#[path = "../inputs.rs"]
mod inputs;

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let _ = inputs::run("instgs_parse", data);
});
