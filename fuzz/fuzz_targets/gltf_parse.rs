//! Fuzz target: glTF (.glb or .gltf JSON) with KHR_gaussian_splatting, on arbitrary bytes
//! (fuzz/inputs.rs). Run from the repository root:
//! `cargo +nightly fuzz run gltf_parse fuzz/seeds/gltf_parse`.
#![no_main]
#[path = "../inputs.rs"]
mod inputs;

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let _ = inputs::run("gltf_parse", data);
});
