//! Fuzz target: a .gltf/.glb file read from a folder that also holds its buffer file and what a
//! hostile file may name instead (a device, a FIFO, a folder, links out; fuzz/inputs.rs), so the
//! URI resolution and confinement are fuzzed with the rest. Run from the repository root:
//! `cargo +nightly fuzz run gltf_files fuzz/seeds/gltf_files`.
#![no_main]
#[path = "../inputs.rs"]
mod inputs;

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let _ = inputs::run("gltf_files", data);
});
