//! The `.instgs` file: write → read is exact (f32 offsets) or f16-rounded (f16 offsets);
//! malformed files are refused with clear errors; random corruption never panics.
mod common;

use common::*;
use glam::{Quat, Vec3};
use instgs_vk::formats::instgs::{self, Dtype};
use instgs_vk::model::instanced::{Group, Instance, InstancedScene, Offsets, Similarity};

fn scene(rng: &mut Rng, deg: u32) -> InstancedScene {
    let groups = (0..2)
        .map(|g| {
            let (t, k) = (7 + g, 3 + g);
            let instances = (0..k)
                .map(|i| Instance {
                    id: format!("{g}-{i}"),
                    transform: Similarity::from_parts(
                        Quat::from_xyzw(rng.normal(), rng.normal(), rng.normal(), rng.normal()),
                        rng.range(0.5, 2.0),
                        Vec3::new(rng.normal(), rng.normal(), rng.normal()),
                    ),
                })
                .collect();
            let mut offsets = Offsets::zeros(t * k);
            for p in 0..t * k {
                offsets.d_means[p] = [rng.normal(), rng.normal(), rng.normal()];
                offsets.d_sh0[p] = [rng.normal(), rng.normal(), rng.normal()];
                offsets.d_opacities[p] = rng.normal();
            }
            Group { name: format!("object {g}"), template: random_scene(rng, t, deg), instances, offsets }
        })
        .collect();
    InstancedScene { sh_degree: deg, background: random_scene(rng, 5, deg), groups }
}

#[test]
fn write_then_read_is_exact() {
    let mut rng = Rng::new(1);
    let dir = tempdir("instgs_roundtrip");
    for deg in 0..=3 {
        let s = scene(&mut rng, deg);
        let path = dir.join(format!("s{deg}.instgs"));
        instgs::write(&s, &path, Dtype::F32).unwrap();
        assert_eq!(instgs::read(&path).unwrap(), s, "degree {deg}");
        // f16 offsets: the same scene with offsets rounded to half precision, a smaller file.
        let path16 = dir.join(format!("s{deg}_f16.instgs"));
        instgs::write(&s, &path16, Dtype::F16).unwrap();
        let back = instgs::read(&path16).unwrap();
        let mut want = s.clone();
        for g in &mut want.groups {
            let r = |v: &mut f32| *v = half::f16::from_f32(*v).to_f32();
            g.offsets.d_means.iter_mut().flatten().for_each(r);
            g.offsets.d_sh0.iter_mut().flatten().for_each(r);
            g.offsets.d_opacities.iter_mut().for_each(r);
        }
        assert_eq!(back, want);
        assert!(std::fs::metadata(&path16).unwrap().len() < std::fs::metadata(&path).unwrap().len());
    }
    // A scene without background Gaussians.
    let mut s = scene(&mut rng, 1);
    s.background = instgs_vk::model::scene::Scene { sh_degree: 1, ..Default::default() };
    let bytes = instgs::to_bytes(&s, Dtype::F32);
    assert_eq!(instgs::from_bytes(&bytes, "mem").unwrap(), s);
}

/// The compressed file ([`instgs::write_compressed`]): the background's and the templates'
/// Gaussians read back as the one SOG bundle of them decodes (its k-means weighing a template's
/// Gaussian once per instance), the offsets within half a step of the source (q8), the
/// instances exact; version 4, smaller than the f16 file; a scene without background Gaussians;
/// pq8 offsets beside SOG parameters; offsets q8 cannot hold refused; a damaged bundle or
/// damaged codes refused with their section named; a version-3 file (a bundle per part) still
/// reads.
#[test]
fn compressed_file_holds_one_sog_bundle_and_q8_offsets() {
    use instgs_vk::formats::{q8, sog};
    let mut rng = Rng::new(4);
    let mut s = scene(&mut rng, 3);
    s.background = random_scene(&mut rng, 2000, 3);
    let dir = tempdir("instgs_compressed");
    let (path, path16) = (dir.join("c.instgs"), dir.join("f16.instgs"));
    instgs::write_compressed(&s, &path).unwrap();
    instgs::write(&s, &path16, Dtype::F16).unwrap();
    let back = instgs::read(&path).unwrap();
    // The Gaussians: the bundle of all parts, cut at the parts' counts.
    let mut all = s.background.clone();
    let mut weights = vec![1.0f32; all.len()];
    for g in &s.groups {
        all.append(&g.template);
        weights.resize(all.len(), g.instances.len() as f32);
    }
    let decoded = sog::sog_from_bundle(&sog::bundle_bytes(&all, Some(&weights)).unwrap(), "x").unwrap();
    let mut start = 0;
    let mut cut = |n: usize| {
        start += n;
        decoded.select(&(start - n..start).collect::<Vec<_>>())
    };
    assert!(back.background == cut(s.background.len()), "the background is the bundle's first Gaussians");
    for (g, source) in back.groups.iter().zip(&s.groups) {
        assert!(g.template == cut(source.template.len()), "each template is the bundle's next Gaussians");
        assert_eq!(g.instances, source.instances);
        // Offsets: a multiple of the kind's step, within half a step of the source.
        let codes = q8::OffsetCodes::encode(&source.offsets).unwrap();
        assert!(g.offsets == codes.decode(source.offsets.d_opacities.len(), "x").unwrap());
        let kinds =
            |o: &instgs_vk::model::instanced::Offsets| [o.d_means.concat(), o.d_sh0.concat(), o.d_opacities.clone()];
        for ((got, want), step) in kinds(&g.offsets).iter().zip(kinds(&source.offsets)).zip(codes.steps) {
            let rms = (want.iter().map(|x| x * x).sum::<f32>() / want.len() as f32).sqrt();
            let largest = want.iter().fold(0.0f32, |m, x| m.max(x.abs()));
            assert!((step - (q8::STEP_OF_RMS * rms).max(largest / 127.0)).abs() <= 1e-6 * step);
            for (a, b) in got.iter().zip(&want) {
                assert!((a - b).abs() <= 0.5 * step * (1.0 + 1e-5), "{a} against {b}, step {step}");
                assert!((a / step - (a / step).round()).abs() < 1e-4, "{a} is not a multiple of {step}");
            }
        }
    }
    // Coded again, a decoded scene's offsets are the same (the player saves a file as stored).
    let again =
        instgs::from_bytes(&instgs::to_bytes_stored(&back, instgs::Storage::COMPRESSED).unwrap(), "again").unwrap();
    for (a, b) in again.groups.iter().zip(&back.groups) {
        assert!(a.offsets == b.offsets, "q8 offsets are coded again exactly");
    }
    let bytes = std::fs::read(&path).unwrap();
    assert_eq!(split(&bytes).0["version"], 4);
    let (size, size16) = (bytes.len(), std::fs::metadata(&path16).unwrap().len() as usize);
    assert!(size * 3 < size16, "{size} against {size16} bytes");
    // No background Gaussians.
    let mut empty = s.clone();
    empty.background = instgs_vk::model::scene::Scene { sh_degree: 3, ..Default::default() };
    instgs::write_compressed(&empty, &path).unwrap();
    let read = instgs::read(&path).unwrap();
    assert!(read.background.is_empty() && read.groups[0].template.len() == s.groups[0].template.len());
    // pq8 offsets with SOG parameters.
    let pq = instgs::to_bytes_stored(&s, instgs::Storage { offsets: Dtype::Pq8, params: Dtype::Sog }).unwrap();
    assert_eq!(instgs::from_bytes(&pq, "pq").unwrap().background, back.background);
    // An offset near ±f32::MAX: q8's ±127 steps would decode past f32, so the file is refused,
    // named, and not written (found by fuzzing instgs_parse).
    let mut far = s.clone();
    far.groups[0].offsets.d_sh0[0][0] = f32::MAX;
    let far_path = dir.join("far.instgs");
    let e = format!("{:#}", instgs::write_compressed(&far, &far_path).unwrap_err());
    assert!(e.contains("far.instgs") && e.contains("q8") && !e.contains('\n'), "{e}");
    assert!(!far_path.exists());
    // A damaged bundle or damaged codes (re-sealed, so the checksum passes): the section is named.
    let (h, data) = split(&bytes_of(&s));
    for (index, name) in [(0, "gaussians/sog"), (2, "group/0/d_codes")] {
        let sec = &h["sections"][index];
        assert_eq!(sec["name"], name);
        let mut data = data.clone();
        let at = sec["offset"].as_u64().unwrap() as usize;
        data[at..at + 4].iter_mut().for_each(|b| *b ^= 0xff);
        let e = format!("{:#}", instgs::from_bytes(&join(&h, &data), "bad.instgs").unwrap_err());
        assert!(e.starts_with("bad.instgs") && e.contains(name), "{e}");
    }
    // A step of zero: refused, the section named.
    let sec = &h["sections"][1];
    assert_eq!(sec["name"], "group/0/d_steps");
    let mut zero = data.clone();
    let at = sec["offset"].as_u64().unwrap() as usize;
    zero[at..at + 4].copy_from_slice(&0.0f32.to_le_bytes());
    let e = format!("{:#}", instgs::from_bytes(&join(&h, &zero), "bad.instgs").unwrap_err());
    assert!(e.contains("group/0/d_codes") && e.contains("finite and positive"), "{e}");
    // Version 3 (written by earlier builds: a SOG bundle per part, f16 offsets) still reads.
    let seeds = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("fuzz/seeds/instgs_parse");
    let (v3, f32v2) =
        (instgs::read(&seeds.join("sog-v3.instgs")).unwrap(), instgs::read(&seeds.join("f32-v2.instgs")).unwrap());
    assert_eq!(split(&std::fs::read(seeds.join("sog-v3.instgs")).unwrap()).0["version"], 3);
    assert_eq!(v3.background.len(), f32v2.background.len());
    assert_eq!(
        v3.groups.iter().map(|g| g.template.len()).collect::<Vec<_>>(),
        f32v2.groups.iter().map(|g| g.template.len()).collect::<Vec<_>>()
    );
}

fn bytes_of(s: &InstancedScene) -> Vec<u8> {
    instgs::to_bytes_stored(s, instgs::Storage::COMPRESSED).unwrap()
}

/// (header JSON, data) of a version-2 file (its CRC-32 trailer left off).
fn split(bytes: &[u8]) -> (serde_json::Value, Vec<u8>) {
    let len = u32::from_le_bytes(bytes[8..12].try_into().unwrap()) as usize;
    let start = (12 + len).div_ceil(16) * 16;
    (serde_json::from_slice(&bytes[12..12 + len]).unwrap(), bytes[start..bytes.len() - 4].to_vec())
}

fn join(header: &serde_json::Value, data: &[u8]) -> Vec<u8> {
    let json = serde_json::to_vec(header).unwrap();
    let mut out = b"INSTGS\0\0".to_vec();
    out.extend_from_slice(&(json.len() as u32).to_le_bytes());
    out.extend_from_slice(&json);
    while !out.len().is_multiple_of(16) {
        out.push(0);
    }
    out.extend_from_slice(data);
    // Sealed with a fresh CRC-32, so the reader's other checks are what refuse an edit.
    let crc = crc32fast::hash(&out);
    out.extend_from_slice(&crc.to_le_bytes());
    out
}

#[test]
fn malformed_files_are_refused_with_clear_errors() {
    let mut rng = Rng::new(2);
    let s = scene(&mut rng, 1);
    let good = instgs::to_bytes(&s, Dtype::F32);
    let (h, data) = split(&good);
    assert_eq!(instgs::from_bytes(&join(&h, &data), "x").unwrap(), s);
    let err = |bytes: &[u8]| format!("{:#}", instgs::from_bytes(bytes, "bad.instgs").unwrap_err());
    let edit = |f: &dyn Fn(&mut serde_json::Value)| {
        let mut h = h.clone();
        f(&mut h);
        err(&join(&h, &data))
    };
    let cases: Vec<(String, &str)> = vec![
        (err(b"PLY\n"), "magic"),
        (err(&good[..11]), "magic"),
        (err(&good[..good.len() / 2]), "damaged"),
        (err(&[&good[..8], &u32::MAX.to_le_bytes()[..], &good[12..]].concat()), "header length"),
        (err(&join(&serde_json::json!("{"), &data)), "format"),
        (
            {
                let mut b = good.clone();
                b[12] = b'[';
                err(&b)
            },
            "malformed JSON",
        ),
        (edit(&|h| h["version"] = 5.into()), "version 5 is not supported"),
        (edit(&|h| h["param_dtype"] = "f16".into()), "not a parameter storage"),
        (edit(&|h| h["format"] = "ply".into()), "format"),
        (edit(&|h| h["groups"][0]["template_gaussians"] = 8.into()), "shape"),
        (edit(&|h| h["background_gaussians"] = 4.into()), "shape"),
        (edit(&|h| h["sections"][3]["offset"] = 1_000_000_000u64.into()), "runs past the end"),
        (edit(&|h| h["sections"][3]["bytes"] = 8.into()), "bytes"),
        (edit(&|h| h["sections"][2]["name"] = "background/means".into()), "twice"),
        (
            edit(&|h| {
                h["sections"].as_array_mut().unwrap().pop();
            }),
            "sections",
        ),
        (edit(&|h| h["sections"][0]["dtype"] = "f16".into()), "expected F32"),
        (edit(&|h| h["sh_degree"] = 4.into()), "SH degree 4"),
        (edit(&|h| h["groups"][0]["instances"][0]["transform"][0][0] = 3.0.into()), "uniform scale"),
        (edit(&|h| h["groups"][0]["instances"][0]["transform"][3][0] = 1.0.into()), "last row"),
        (edit(&|h| h["groups"][0]["instances"] = serde_json::json!([])), "shape"),
        (edit(&|h| h["offset_dtype"] = "f64".into()), "unknown variant"),
    ];
    for (e, want) in &cases {
        assert!(e.starts_with("bad.instgs"), "error does not name the file: {e}");
        assert!(e.contains(want), "expected {want:?} in: {e}");
    }
    // A NaN in the data (sealed again: the value check refuses it).
    let mut nan = data.clone();
    nan[..4].copy_from_slice(&f32::NAN.to_le_bytes());
    let e = err(&join(&h, &nan));
    assert!(e.contains("non-finite"), "{e}");
}

#[test]
fn corrupted_files_never_panic() {
    // A deterministic fuzz smoke test (the cargo-fuzz target in fuzz/ runs the same parser
    // for longer): bit flips, byte runs, truncations and header edits of a valid file.
    let mut rng = Rng::new(3);
    let s = scene(&mut rng, 2);
    for (good, rounds) in [(instgs::to_bytes(&s, Dtype::F16), 3000), (bytes_of(&s), 600)] {
        corrupt(&mut rng, &good, rounds);
    }
}

/// `rounds` corruptions of `good`; some parse, most do not, none panics.
fn corrupt(rng: &mut Rng, good: &[u8], rounds: usize) {
    let header_end = 12 + u32::from_le_bytes(good[8..12].try_into().unwrap()) as usize;
    let mut parsed = 0;
    for round in 0..rounds {
        let mut b = good.to_vec();
        match round % 4 {
            0 => {
                for _ in 0..1 + rng.u32() % 8 {
                    let i = (rng.u32() as usize) % b.len();
                    b[i] ^= 1 << (rng.u32() % 8);
                }
            }
            1 => {
                // Inside the JSON header: digits and punctuation.
                let i = 12 + (rng.u32() as usize) % (header_end - 12);
                b[i] = b"0123456789-.e,:[]{}\""[(rng.u32() % 20) as usize];
            }
            2 => b.truncate((rng.u32() as usize) % b.len()),
            _ => {
                let i = (rng.u32() as usize) % b.len();
                let n = (1 + rng.u32() % 64) as usize;
                for j in i..(i + n).min(b.len()) {
                    b[j] = rng.u32() as u8;
                }
            }
        }
        if instgs::from_bytes(&b, "fuzz").is_ok() {
            parsed += 1;
        }
    }
    // Flips inside f16 offsets still parse; most corruptions do not.
    assert!(parsed > 0 && parsed < rounds, "{parsed}");
}
