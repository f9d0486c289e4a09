//! The `.instgs` parser on arbitrary bytes: it must return an error or a valid scene, never
//! panic, hang or allocate without bound. Run: `cargo +nightly fuzz run instgs_parse`
//! (seed corpus: `fuzz/corpus/instgs_parse/`).
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok(scene) = instgs_vk::formats::instgs::from_bytes(data, "fuzz") {
        // What parses is a valid scene that writes back and reads again to the same scene.
        let bytes = instgs_vk::formats::instgs::to_bytes(&scene, instgs_vk::formats::instgs::Dtype::F32);
        assert_eq!(instgs_vk::formats::instgs::from_bytes(&bytes, "fuzz").unwrap(), scene);
    }
});
