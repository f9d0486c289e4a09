//! Fuzz target: training, instanced, pipeline and render configurations, on arbitrary bytes (fuzz/inputs.rs). Run from the repository root:
//! `cargo +nightly fuzz run config_toml fuzz/seeds/config_toml`.
#![no_main]
#[path = "../inputs.rs"]
mod inputs;

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let _ = inputs::run("config_toml", data);
});
