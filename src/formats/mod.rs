//! Scene files of other 3DGS tools: chosen by content (magic bytes, `meta.json`), not by name.
//!
//! | format | read | written by `convert` | lossy |
//! |---|---|---|---|
//! | Inria 3DGS PLY | yes | `.ply` | no |
//! | SuperSplat compressed PLY (`chunk` + packed `vertex`, optional `sh`) | yes | `.compressed.ply` | yes: 11/10/11-bit positions and log-scales per 256-splat chunk, 2+10+10+10-bit rotations, 8-bit colour and opacity, 8-bit SH in ±4 |
//! | Niantic `.spz` (versions 2 and 3: gzip; 4: zstd streams) | yes | `.spz` (version 4) | yes: 24-bit fixed-point positions (12 fractional bits when written), 8-bit log-scales (1/16), rotations (smallest three, 10 bits), 8-bit colour (±1/0.15·½), opacity and SH (±1, 1/128) |
//! | PlayCanvas SOG versions 1 and 2 (`meta.json` + WebP images) | yes | version 2 | yes: 16-bit log-positions, 256-entry codebooks, 8-bit rotations, palettised SH |
//! | antimatter15 `.splat` (32-byte rows, no SH) | yes | `.splat` | yes: 8-bit colour, opacity and rotation; SH dropped |
//! | glTF 2.0 with `KHR_gaussian_splatting` (`.glb`, `.gltf`; quantised accessors and `KHR_gaussian_splatting_compression_spz_2` read) | yes | `.glb`, `.gltf` (an `.instgs` scene with its templates shared, [`gltf`]) | no: float accessors |
//! | 3D Tiles 1.1 (`tileset.json`, one `.glb` per tile, SPZ-compressed: what CesiumJS draws) | yes (as one plain scene) | `…tileset.json` (a tile per instance, placed by its transform) | yes: as `.spz` (version 3 inside: gzip, smallest-three rotations) |
//! | `.instgs` (ours, `docs/format.md`) | yes | `.instgs` | f16 offsets on request |
//!
//! Conventions on reading: every scene comes out in the Inria/COLMAP frame the PLY formats use
//! (x right, y down, z forward). glTF is +Y up, +Z forward: a half turn about z ([`gltf`]).
//! `.spz` stores x right, y up, z back (its README), so y and z
//! are negated: means (x, −y, −z), quaternions (w, x, −y, −z) and each SH coefficient by the
//! parity of its basis function under that turn (as Niantic's own converter does). Opacities
//! of exactly 0 or 1 — an infinite logit, which splat-transform and spz-js write into PLYs for
//! fully opaque splats — are clamped to ±ln 1019 (the centre of the outer halves of the outer
//! 8-bit bins, the rule of our compressed-PLY reader); NaN anywhere stays an error.

pub mod gltf;
pub mod info;
pub mod instgs;
pub mod ply;
pub mod pq8;
pub mod q8;
pub mod quant;
pub mod sog;
pub mod splat;
pub mod spz;

use std::io::Read;
use std::path::Path;

use anyhow::{bail, Context, Result};

use crate::model::instanced::InstancedScene;
use crate::model::scene::Scene;
use sog::{read_sog, write_sog};
use splat::{read_splat, write_splat};
use spz::{read_spz, write_spz};

/// The scene formats we read.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Format {
    Ply,
    Spz,
    Sog,
    Splat,
    Gltf,
    Tiles,
    Instgs,
}

impl Format {
    pub fn name(self) -> &'static str {
        match self {
            Format::Ply => "PLY",
            Format::Spz => ".spz",
            Format::Sog => "SOG",
            Format::Splat => ".splat",
            Format::Gltf => "glTF",
            Format::Tiles => "3D Tiles",
            Format::Instgs => ".instgs",
        }
    }
}

/// What we read, for errors.
pub const READABLE: &str =
    "PLY (Inria 3DGS or SuperSplat compressed), .spz (versions 2-4), SOG versions 1-2 (a meta.json \
                            with its WebP images, their folder, or a .sog bundle of them), .splat (32-byte rows), glTF (.glb, .gltf with KHR_gaussian_splatting, SPZ-compressed or not), 3D Tiles (a tileset.json of such glTF) and .instgs";

/// The format of `path` by its content (a folder holding `meta.json` is SOG; `.splat` has no
/// magic bytes and is taken by its extension when its size is a multiple of 32).
pub fn detect(path: &Path) -> Result<Format> {
    let what = path.display();
    if path.is_dir() {
        if path.join("meta.json").is_file() {
            return Ok(Format::Sog);
        }
        bail!("{what}: a folder without meta.json; we read {READABLE}");
    }
    let mut head = [0u8; 16];
    let n = {
        let mut f = std::fs::File::open(path).with_context(|| format!("{what}: cannot open"))?;
        let mut n = 0;
        while n < head.len() {
            let k = f.read(&mut head[n..]).with_context(|| format!("{what}: cannot read"))?;
            if k == 0 {
                break;
            }
            n += k;
        }
        n
    };
    let head = &head[..n];
    let ext = path.extension().map(|e| e.to_string_lossy().to_ascii_lowercase()).unwrap_or_default();
    // .splat has no magic of its own: its name decides before any sniffing (a legal file may
    // start with bytes that look like another format's).
    if ext == "splat" {
        let len = std::fs::metadata(path).with_context(|| format!("{what}: cannot read"))?.len();
        if len % 32 != 0 || len == 0 {
            bail!("{what}: a .splat file holds 32-byte rows, but it is {len} bytes long");
        }
        return Ok(Format::Splat);
    }
    if head.starts_with(b"ply\n") || head.starts_with(b"ply\r\n") {
        return Ok(Format::Ply);
    }
    if head.starts_with(b"NGSP") || head.starts_with(&[0x1f, 0x8b]) {
        return Ok(Format::Spz);
    }
    if head.starts_with(b"INSTGS") {
        return Ok(Format::Instgs);
    }
    if head.starts_with(b"glTF") {
        return Ok(Format::Gltf);
    }
    if head.starts_with(b"PK\x03\x04") && sog::is_sog_bundle(path) {
        return Ok(Format::Sog);
    }
    let first = head.iter().find(|b| !b.is_ascii_whitespace());
    let named_meta = path.file_name().is_some_and(|n| n.eq_ignore_ascii_case("meta.json"));
    if first == Some(&b'{') && (named_meta || is_sog_meta(path)) {
        return Ok(Format::Sog);
    }
    // A tileset has a glTF-like `asset` too: its `root` tells them apart.
    if first == Some(&b'{') && gltf::looks_like_tileset(path) {
        return Ok(Format::Tiles);
    }
    if first == Some(&b'{') && gltf::looks_like_gltf(head, path) {
        return Ok(Format::Gltf);
    }
    let detected = if head.starts_with(b"\x89PNG") {
        "a PNG image"
    } else if head.starts_with(&[0xff, 0xd8, 0xff]) {
        "a JPEG image"
    } else if head.starts_with(b"PK\x03\x04") {
        "a zip archive without a SOG meta.json"
    } else if head.starts_with(b"RIFF") {
        "a RIFF/WebP image (SOG images are read through their meta.json)"
    } else if first == Some(&b'{')
        && std::fs::read(path).is_ok_and(|b| serde_json::from_slice::<serde_json::Value>(&b).is_ok())
    {
        "JSON that is not a SOG meta.json"
    } else if head.is_empty() {
        "an empty file"
    } else if head.iter().all(|b| b.is_ascii_graphic() || b.is_ascii_whitespace()) {
        "text"
    } else {
        "unknown binary data"
    };
    bail!("{what}: not a scene file we read ({detected}); we read {READABLE}")
}

/// Bytes the scene occupies on disk (a SOG folder: its meta.json and the images it names; a
/// `.sog` bundle: the file).
pub fn file_bytes(path: &Path) -> Result<u64> {
    let len = |p: &Path| std::fs::metadata(p).map(|m| m.len()).with_context(|| format!("{}: cannot read", p.display()));
    if detect(path)? != Format::Sog || (path.is_file() && sog::is_sog_bundle(path)) {
        return len(path);
    }
    let meta = if path.is_dir() { path.join("meta.json") } else { path.to_path_buf() };
    let dir = meta.parent().unwrap_or(Path::new("."));
    let v: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&meta)?)?;
    let mut total = len(&meta)?;
    if let Some(o) = v.as_object() {
        for part in o.values() {
            for f in part.get("files").and_then(|f| f.as_array()).into_iter().flatten() {
                if let Some(name) = f.as_str() {
                    total += len(&dir.join(name))?;
                }
            }
        }
    }
    Ok(total)
}

fn is_sog_meta(path: &Path) -> bool {
    let Ok(text) = std::fs::read_to_string(path) else { return false };
    serde_json::from_str::<serde_json::Value>(&text)
        .is_ok_and(|v| v.get("means").is_some() && v.get("quats").is_some() && v.get("sh0").is_some())
}

/// Reads a plain scene in any format we read (an `.instgs` file is refused: it is instanced,
/// see [`crate::formats::AnyScene`]).
pub fn read_scene(path: &Path) -> Result<Scene> {
    let what = path.display().to_string();
    let scene = match detect(path)? {
        Format::Ply => return crate::formats::ply::read_ply(path),
        Format::Spz => {
            let bytes = std::fs::read(path).with_context(|| format!("{what}: cannot read"))?;
            read_spz(&what, &bytes)?
        }
        Format::Sog => read_sog(path)?,
        // An instanced glTF is a plain scene to every other tool: expanded here.
        Format::Gltf => match gltf::read(path)? {
            gltf::GltfScene::Plain(s) => s,
            gltf::GltfScene::Instanced(s) => s.expand(),
        },
        Format::Splat => {
            let bytes = std::fs::read(path).with_context(|| format!("{what}: cannot read"))?;
            read_splat(&what, &bytes)?
        }
        Format::Tiles => gltf::read_tileset(path)?,
        Format::Instgs => bail!(
            "{what}: an instanced scene (.instgs); this command takes a plain scene — `instgs-vk convert {what} OUT.ply` expands it"
        ),
    };
    scene.validate(&what)?;
    Ok(scene)
}

/// Writes `scene` in the format `out`'s name chooses: `.compressed.ply`, `.ply`, `.spz`,
/// `…meta.json` (SOG, a folder), `.sog` (SOG, one zip file), `.glb`/`.gltf` or `.splat` (its SH bands dropped, said on stderr). Every writer refuses a
/// scene the readers would refuse (`Scene::validate`).
pub fn write_scene(scene: &Scene, out: &Path) -> Result<()> {
    let name = out.file_name().map(|n| n.to_string_lossy().to_ascii_lowercase()).unwrap_or_default();
    if name.ends_with(".compressed.ply") {
        crate::formats::ply::write_compressed_ply(scene, out)
    } else if name.ends_with(".ply") {
        crate::formats::ply::write_ply(scene, out)
    } else if name.ends_with(".spz") {
        write_spz(scene, out)
    } else if name.ends_with("meta.json") {
        write_sog(scene, out)
    } else if name.ends_with(".sog") {
        sog::write_sog_bundle(scene, out)
    } else if name.ends_with(".glb") || name.ends_with(".gltf") {
        gltf::write_gltf(scene, out, gltf::Accessors::Float)
    } else if name.ends_with(".splat") {
        if scene.sh_degree > 0 {
            eprintln!("note: .splat holds no SH bands: degree {} dropped", scene.sh_degree);
        }
        write_splat(scene, out)
    } else {
        bail!(
            "{}: cannot write this format; the output's name chooses: .ply (Inria), .compressed.ply (SuperSplat), .spz (version 4), meta.json (SOG version 2, its images beside it), .sog (the same in one zip), .glb or .gltf (glTF with KHR_gaussian_splatting), tileset.json (3D Tiles, SPZ-compressed glTF tiles beside it), .splat, .json (an instanced scene's scene graph) or .instgs (an instanced scene)",
            out.display()
        )
    }
}

/// A scene file of either kind: a plain scene in any format [`crate::formats`] reads, or an
/// `.instgs` instanced scene (chosen by content).
pub enum AnyScene {
    Plain(Scene),
    Instanced(InstancedScene),
}

impl AnyScene {
    pub fn read(path: &Path) -> Result<AnyScene> {
        match detect(path)? {
            Format::Instgs => Ok(AnyScene::Instanced(instgs::read(path)?)),
            Format::Gltf => Ok(match gltf::read(path)? {
                gltf::GltfScene::Plain(s) => AnyScene::Plain(s),
                gltf::GltfScene::Instanced(s) => AnyScene::Instanced(s),
            }),
            _ => Ok(AnyScene::Plain(read_scene(path)?)),
        }
    }

    /// Splats rendered (an instanced scene's expanded count).
    pub fn splats(&self) -> usize {
        match self {
            AnyScene::Plain(s) => s.len(),
            AnyScene::Instanced(s) => s.splats(),
        }
    }

    pub fn sh_degree(&self) -> u32 {
        match self {
            AnyScene::Plain(s) => s.sh_degree,
            AnyScene::Instanced(s) => s.sh_degree,
        }
    }

    /// World-space means of every splat (expanded).
    pub fn means(&self) -> std::borrow::Cow<'_, [[f32; 3]]> {
        match self {
            AnyScene::Plain(s) => std::borrow::Cow::Borrowed(&s.means),
            AnyScene::Instanced(s) => std::borrow::Cow::Owned(s.expanded_means()),
        }
    }
}

/// `instgs-vk convert`: `path` (any readable scene) to `out`, the format chosen by `out`'s name
/// ([`write_scene`]); an instanced scene to `.json` writes its scene graph, to `.glb`/`.gltf`
/// an instanced glTF (templates shared) unless `expand`; glTF's attributes as `accessors` says
/// (quantised only to .glb/.gltf, refused before reading otherwise); an instanced scene to
/// `.instgs` with f32 offsets and parameters, or with `compress` as
/// [`instgs::write_compressed`] writes it (refused before reading for other outputs).
pub fn convert(path: &Path, out: &Path, expand: bool, accessors: gltf::Accessors, compress: bool) -> Result<()> {
    let name = out.file_name().map(|n| n.to_string_lossy().to_ascii_lowercase()).unwrap_or_default();
    let gltf_out = name.ends_with(".glb") || name.ends_with(".gltf");
    if accessors == gltf::Accessors::Quantized && !gltf_out {
        bail!("{}: --quantize writes .glb or .gltf only", out.display());
    }
    if compress && !name.ends_with(".instgs") {
        bail!("{}: --compress writes .instgs only", out.display());
    }
    let scene = AnyScene::read(path)?;
    if name.ends_with(".instgs") {
        let AnyScene::Instanced(s) = &scene else {
            bail!("{}: an .instgs file holds an instanced scene; {} is plain", out.display(), path.display())
        };
        match compress {
            true => instgs::write_compressed(s, out)?,
            false => instgs::write(s, out, instgs::Dtype::F32)?,
        }
        eprintln!("wrote {} ({} bytes)", out.display(), file_bytes(out)?);
        return Ok(());
    }
    if name.ends_with("tileset.json") {
        match &scene {
            AnyScene::Plain(s) => gltf::write_tileset(s, out)?,
            AnyScene::Instanced(s) => gltf::write_instanced_tileset(s, out)?,
        }
        eprintln!("wrote {} and its tiles", out.display());
        return Ok(());
    }
    match (&scene, name.ends_with(".json") && !name.ends_with("meta.json")) {
        (AnyScene::Instanced(s), false) if gltf_out && !expand => gltf::write_instanced_gltf(s, out, accessors)?,
        (AnyScene::Plain(s), false) if gltf_out => gltf::write_gltf(s, out, accessors)?,
        (AnyScene::Instanced(s), false) if gltf_out => gltf::write_gltf(&s.expand(), out, accessors)?,
        (AnyScene::Instanced(s), true) => {
            let text = serde_json::to_string_pretty(&crate::model::instanced::scene_graph(s))?;
            crate::util::write_atomic(out, |f| {
                use std::io::Write;
                f.write_all(text.as_bytes())
            })?;
        }
        (AnyScene::Plain(_), true) => {
            bail!("{}: a scene graph (.json) comes from an instanced scene; {} is plain", out.display(), path.display())
        }
        (AnyScene::Plain(s), false) => crate::formats::write_scene(s, out)?,
        (AnyScene::Instanced(s), false) => crate::formats::write_scene(&s.expand(), out)?,
    }
    eprintln!("wrote {}", out.display());
    Ok(())
}
