//! Fuzz target: instance mask PNG, on arbitrary bytes (fuzz/inputs.rs). Run from the repository root:
//! `cargo +nightly fuzz run mask_png fuzz/seeds/mask_png`.
#![no_main]
#[path = "../inputs.rs"]
mod inputs;

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let _ = inputs::run("mask_png", data);
});
