//! Fuzz target: a SOG meta.json read from a folder that also holds its WebP images and what a
//! hostile meta.json may name instead (a device, a FIFO, a folder, links out; fuzz/inputs.rs),
//! so the image names' resolution and confinement are fuzzed with the rest. Run from the
//! repository root: `cargo +nightly fuzz run sog_files fuzz/seeds/sog_files`.
#![no_main]
#[path = "../inputs.rs"]
mod inputs;

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let _ = inputs::run("sog_files", data);
});
