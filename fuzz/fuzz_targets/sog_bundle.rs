//! Fuzz target: a .sog bundle (zip of meta.json and WebP images), on arbitrary bytes
//! (fuzz/inputs.rs). Run from the repository root:
//! `cargo +nightly fuzz run sog_bundle fuzz/seeds/sog_bundle`.
#![no_main]
#[path = "../inputs.rs"]
mod inputs;

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let _ = inputs::run("sog_bundle", data);
});
