//! Fuzz target: training checkpoint, on arbitrary bytes (fuzz/inputs.rs). Run from the repository root:
//! `cargo +nightly fuzz run checkpoint_parse fuzz/seeds/checkpoint_parse`.
#![no_main]
#[path = "../inputs.rs"]
mod inputs;

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let _ = inputs::run("checkpoint_parse", data);
});
