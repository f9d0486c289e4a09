//! Fuzz target: transforms JSON, instances.json, scene graph, labels, on arbitrary bytes (fuzz/inputs.rs). Run from the repository root:
//! `cargo +nightly fuzz run json_inputs fuzz/seeds/json_inputs`.
#![no_main]
#[path = "../inputs.rs"]
mod inputs;

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let _ = inputs::run("json_inputs", data);
});
