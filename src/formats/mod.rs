//! Scene files of other 3DGS tools: chosen by content (magic bytes, `meta.json`), not by name.
//!
//! | format | read | written by `convert` | lossy |
//! |---|---|---|---|
//! | Inria 3DGS PLY | yes | `.ply` | no |
//! | SuperSplat compressed PLY (`chunk` + packed `vertex`, optional `sh`) | yes | `.compressed.ply` | yes: 11/10/11-bit positions and log-scales per 256-splat chunk, 2+10+10+10-bit rotations, 8-bit colour and opacity, 8-bit SH in ±4 |
//! | Niantic `.spz` (versions 2 and 3: gzip; 4: zstd streams) | yes | `.spz` (version 4) | yes: 24-bit fixed-point positions (12 fractional bits when written), 8-bit log-scales (1/16), rotations (smallest three, 10 bits), 8-bit colour (±1/0.15·½), opacity and SH (±1, 1/128) |
//! | PlayCanvas SOG versions 1 and 2 (`meta.json` + WebP images) | yes | version 2 | yes: 16-bit log-positions, 256-entry codebooks, 8-bit rotations, palettised SH |
//! | antimatter15 `.splat` (32-byte rows, no SH) | yes | `.splat` | yes: 8-bit colour, opacity and rotation; SH dropped |
//! | `.instgs` (ours, `docs/format.md`) | yes | `.instgs` | f16 offsets on request |
//!
//! Conventions on reading: every scene comes out in the Inria/COLMAP frame the PLY formats use
//! (x right, y down, z forward). `.spz` stores x right, y up, z back (its README), so y and z
//! are negated: means (x, −y, −z), quaternions (w, x, −y, −z) and each SH coefficient by the
//! parity of its basis function under that turn (as Niantic's own converter does). Opacities
//! of exactly 0 or 1 — an infinite logit, which splat-transform and spz-js write into PLYs for
//! fully opaque splats — are clamped to ±ln 1019 (the centre of the outer halves of the outer
//! 8-bit bins, the rule of our compressed-PLY reader); NaN anywhere stays an error.

pub mod info;
pub mod instgs;
pub mod pq8;
use std::io::Read;
use std::path::{Path, PathBuf};

use anyhow::{anyhow, bail, Context, Result};

use crate::model::scene::{Scene, SH_C0};

/// An opacity logit's bound when the stored opacity is exactly 0 or 1: ln(1019).
pub const OPACITY_LOGIT_LIMIT: f32 = 6.926_577;

/// The scene formats we read.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Format {
    Ply,
    Spz,
    Sog,
    Splat,
    Instgs,
}

impl Format {
    pub fn name(self) -> &'static str {
        match self {
            Format::Ply => "PLY",
            Format::Spz => ".spz",
            Format::Sog => "SOG",
            Format::Splat => ".splat",
            Format::Instgs => ".instgs",
        }
    }
}

/// What we read, for errors.
pub const READABLE: &str =
    "PLY (Inria 3DGS or SuperSplat compressed), .spz (versions 2-4), SOG versions 1-2 (a meta.json \
                            with its WebP images, or their folder), .splat (32-byte rows) and .instgs";

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
    if head.starts_with(b"ply\n") || head.starts_with(b"ply\r\n") {
        return Ok(Format::Ply);
    }
    if head.starts_with(b"NGSP") || head.starts_with(&[0x1f, 0x8b]) {
        return Ok(Format::Spz);
    }
    if head.starts_with(b"INSTGS") {
        return Ok(Format::Instgs);
    }
    let first = head.iter().find(|b| !b.is_ascii_whitespace());
    if first == Some(&b'{') && is_sog_meta(path) {
        return Ok(Format::Sog);
    }
    if ext == "splat" {
        let len = std::fs::metadata(path).with_context(|| format!("{what}: cannot read"))?.len();
        if len % 32 != 0 || len == 0 {
            bail!("{what}: a .splat file holds 32-byte rows, but it is {len} bytes long");
        }
        return Ok(Format::Splat);
    }
    let detected = if head.starts_with(b"\x89PNG") {
        "a PNG image"
    } else if head.starts_with(&[0xff, 0xd8, 0xff]) {
        "a JPEG image"
    } else if head.starts_with(b"PK\x03\x04") {
        "a zip archive (a bundled .sog? unzip it and pass its meta.json)"
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

/// Bytes the scene occupies on disk (a SOG scene: its meta.json and the images it names).
pub fn file_bytes(path: &Path) -> Result<u64> {
    let len = |p: &Path| std::fs::metadata(p).map(|m| m.len()).with_context(|| format!("{}: cannot read", p.display()));
    if detect(path)? != Format::Sog {
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
/// see [`crate::formats::instgs::AnyScene`]).
pub fn read_scene(path: &Path) -> Result<Scene> {
    let what = path.display().to_string();
    let scene = match detect(path)? {
        Format::Ply => return crate::model::scene::read_ply(path),
        Format::Spz => {
            let bytes = std::fs::read(path).with_context(|| format!("{what}: cannot read"))?;
            read_spz(&what, &bytes)?
        }
        Format::Sog => read_sog(path)?,
        Format::Splat => {
            let bytes = std::fs::read(path).with_context(|| format!("{what}: cannot read"))?;
            read_splat(&what, &bytes)?
        }
        Format::Instgs => bail!(
            "{what}: an instanced scene (.instgs); this command takes a plain scene — `instgs-vk convert {what} OUT.ply` expands it"
        ),
    };
    scene.validate(&what)?;
    Ok(scene)
}

/// Writes `scene` in the format `out`'s name chooses: `.compressed.ply`, `.ply`, `.spz`,
/// `…meta.json` (SOG) or `.splat` (its SH bands dropped, said on stderr).
pub fn write_scene(scene: &Scene, out: &Path) -> Result<()> {
    let name = out.file_name().map(|n| n.to_string_lossy().to_ascii_lowercase()).unwrap_or_default();
    if name.ends_with(".compressed.ply") {
        crate::model::scene::write_compressed_ply(scene, out)
    } else if name.ends_with(".ply") {
        crate::model::scene::write_ply(scene, out)
    } else if name.ends_with(".spz") {
        write_spz(scene, out)
    } else if name.ends_with("meta.json") {
        write_sog(scene, out)
    } else if name.ends_with(".splat") {
        if scene.sh_degree > 0 {
            eprintln!("note: .splat holds no SH bands: degree {} dropped", scene.sh_degree);
        }
        write_splat(scene, out)
    } else {
        bail!(
            "{}: cannot write this format; the output's name chooses: .ply (Inria), .compressed.ply (SuperSplat), .spz (version 4), meta.json (SOG version 2, its images beside it), .splat, or .json (an instanced scene's scene graph)",
            out.display()
        )
    }
}

/// An opacity in [0, 1] as a logit, 0 and 1 clamped to ±[`OPACITY_LOGIT_LIMIT`].
pub fn opacity_logit(a: f32) -> f32 {
    let limit = 1.0 / (1.0 + OPACITY_LOGIT_LIMIT.exp());
    let a = a.clamp(limit, 1.0 - limit);
    (a / (1.0 - a)).ln()
}

fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}

/// Sign of SH coefficient k (1..16, band-major, m = −l..l as Inria orders them) when y and z
/// are negated: the parity of its basis function in y and z.
const SH_FLIP_YZ: [f32; 16] = [1.0, -1.0, -1.0, 1.0, -1.0, 1.0, 1.0, -1.0, 1.0, -1.0, 1.0, -1.0, -1.0, 1.0, -1.0, 1.0];

/// Negates y and z of the whole scene (the `.spz` frame ↔ the PLY frame; its own inverse).
fn flip_yz(s: &mut Scene) {
    let coeffs = s.sh_coeffs();
    for m in &mut s.means {
        m[1] = -m[1];
        m[2] = -m[2];
    }
    for q in &mut s.quats {
        q[2] = -q[2];
        q[3] = -q[3];
    }
    for (i, v) in s.sh.iter_mut().enumerate() {
        *v *= SH_FLIP_YZ[(i / 3) % coeffs];
    }
}

// ---------------------------------------------------------------------------------------------
// .spz

const SPZ_COLOR_SCALE: f32 = 0.15;
const SPZ_MAGIC: &[u8; 4] = b"NGSP";

struct SpzHeader {
    version: u32,
    count: usize,
    sh_degree: u32,
    fractional_bits: u32,
}

fn u32_at(b: &[u8], at: usize) -> u32 {
    u32::from_le_bytes([b[at], b[at + 1], b[at + 2], b[at + 3]])
}

fn u64_at(b: &[u8], at: usize) -> u64 {
    u64::from_le_bytes(b[at..at + 8].try_into().expect("8 bytes"))
}

/// Bytes per Gaussian of each `.spz` attribute stream, in file order: positions, alphas,
/// colours, scales, rotations, SH.
fn spz_strides(h: &SpzHeader) -> [usize; 6] {
    let sh = ((h.sh_degree + 1) * (h.sh_degree + 1) - 1) as usize * 3;
    [9, 1, 3, 3, if h.version >= 3 { 4 } else { 3 }, sh]
}

fn check_spz_header(what: &str, h: &SpzHeader) -> Result<()> {
    if !(2..=4).contains(&h.version) {
        bail!("{what}: .spz version {} is not read (versions 2-4 are)", h.version);
    }
    if h.sh_degree > 3 {
        bail!("{what}: .spz SH degree {} is not supported (0..3)", h.sh_degree);
    }
    if h.fractional_bits > 23 {
        bail!("{what}: .spz fractional bits {} out of range (0..23)", h.fractional_bits);
    }
    if h.count == 0 {
        bail!("{what}: the .spz holds no Gaussians");
    }
    Ok(())
}

/// Reads a `.spz` file's bytes (versions 2-3 gzip-compressed, 4 with zstd streams).
pub fn read_spz(what: &str, bytes: &[u8]) -> Result<Scene> {
    if bytes.starts_with(&[0x1f, 0x8b]) {
        let mut gz = flate2::read::GzDecoder::new(bytes);
        let mut head = [0u8; 16];
        gz.read_exact(&mut head).map_err(|e| anyhow!("{what}: not a .spz gzip stream: {e}"))?;
        if &head[..4] != SPZ_MAGIC {
            bail!("{what}: a gzip stream, but not a .spz (no NGSP magic inside)");
        }
        let h = SpzHeader {
            version: u32_at(&head, 4),
            count: u32_at(&head, 8) as usize,
            sh_degree: head[12] as u32,
            fractional_bits: head[13] as u32,
        };
        check_spz_header(what, &h)?;
        if h.version == 4 {
            bail!("{what}: .spz version 4 inside gzip (version 4 files are not gzip-wrapped)");
        }
        let strides = spz_strides(&h);
        let total = h.count.checked_mul(strides.iter().sum()).ok_or_else(|| anyhow!("{what}: count too large"))?;
        // Bounded: a gzip bomb cannot make us allocate more than the header's count implies,
        // and the count itself is bounded by what deflate can expand the file to (1032:1).
        if total as u64 > bytes.len() as u64 * 1032 {
            bail!("{what}: the header's {} Gaussians cannot fit in a {}-byte file", h.count, bytes.len());
        }
        let mut body = Vec::with_capacity(total);
        gz.by_ref()
            .take(total as u64)
            .read_to_end(&mut body)
            .map_err(|e| anyhow!("{what}: corrupt gzip stream: {e}"))?;
        if body.len() < total {
            bail!("{what}: truncated: {} of {} bytes of Gaussian data", body.len(), total);
        }
        let mut streams = Vec::new();
        let mut at = 0;
        for s in strides {
            streams.push(body[at..at + s * h.count].to_vec());
            at += s * h.count;
        }
        return decode_spz(&h, &streams);
    }
    if bytes.len() < 32 || &bytes[..4] != SPZ_MAGIC {
        bail!("{what}: not a .spz file (no NGSP magic or gzip stream)");
    }
    let h = SpzHeader {
        version: u32_at(bytes, 4),
        count: u32_at(bytes, 8) as usize,
        sh_degree: bytes[12] as u32,
        fractional_bits: bytes[13] as u32,
    };
    if h.version != 4 {
        bail!("{what}: a plain NGSP header says version {}, but only version 4 is stored without gzip", h.version);
    }
    check_spz_header(what, &h)?;
    let streams_n = bytes[15] as usize;
    let toc = u32_at(bytes, 16) as usize;
    let strides = spz_strides(&h);
    let expected = strides.iter().filter(|&&s| s > 0).count();
    if streams_n != expected {
        bail!("{what}: {streams_n} attribute streams; SH degree {} needs {expected}", h.sh_degree);
    }
    let toc_end = toc.checked_add(streams_n * 16).filter(|&e| toc >= 32 && e <= bytes.len());
    let Some(toc_end) = toc_end else { bail!("{what}: the table of contents lies outside the file") };
    let mut at = toc_end;
    let mut streams = Vec::new();
    let mut k = 0;
    for s in strides {
        if s == 0 {
            streams.push(Vec::new());
            continue;
        }
        let compressed = u64_at(bytes, toc + k * 16) as usize;
        let size = u64_at(bytes, toc + k * 16 + 8) as usize;
        k += 1;
        if size != s * h.count {
            bail!("{what}: stream {k} holds {size} bytes, {} Gaussians need {}", h.count, s * h.count);
        }
        let end = at.checked_add(compressed).filter(|&e| e <= bytes.len());
        let Some(end) = end else { bail!("{what}: truncated: stream {k} runs past the end of the file") };
        let data = zstd::bulk::decompress(&bytes[at..end], size)
            .map_err(|e| anyhow!("{what}: corrupt zstd stream {k}: {e}"))?;
        if data.len() != size {
            bail!("{what}: stream {k} decompresses to {} bytes, expected {size}", data.len());
        }
        streams.push(data);
        at = end;
    }
    if at != bytes.len() {
        bail!("{what}: {} bytes follow the last stream", bytes.len() - at);
    }
    decode_spz(&h, &streams)
}

fn decode_spz(h: &SpzHeader, st: &[Vec<u8>]) -> Result<Scene> {
    let n = h.count;
    let coeffs = ((h.sh_degree + 1) * (h.sh_degree + 1)) as usize;
    let mut s = Scene { sh_degree: h.sh_degree, ..Default::default() };
    let unit = 1.0 / (1u32 << h.fractional_bits) as f32;
    let rot_bytes = if h.version >= 3 { 4 } else { 3 };
    for i in 0..n {
        let p = &st[0][i * 9..i * 9 + 9];
        s.means.push(std::array::from_fn(|a| {
            let raw = p[a * 3] as u32 | (p[a * 3 + 1] as u32) << 8 | (p[a * 3 + 2] as u32) << 16;
            ((raw << 8) as i32 >> 8) as f32 * unit
        }));
        s.opacities.push(opacity_logit(st[1][i] as f32 / 255.0));
        let c = &st[2][i * 3..i * 3 + 3];
        s.sh.extend(c.iter().map(|&b| (b as f32 / 255.0 - 0.5) / SPZ_COLOR_SCALE));
        for k in 1..coeffs {
            for ch in 0..3 {
                let b = st[5][(i * (coeffs - 1) + k - 1) * 3 + ch];
                s.sh.push((b as f32 - 128.0) / 128.0);
            }
        }
        let sc = &st[3][i * 3..i * 3 + 3];
        s.scales.push(std::array::from_fn(|a| sc[a] as f32 / 16.0 - 10.0));
        let r = &st[4][i * rot_bytes..(i + 1) * rot_bytes];
        // Stored (x, y, z, w); ours (w, x, y, z).
        let xyzw = if h.version >= 3 { unpack_smallest_three(r) } else { first_three(r) };
        s.quats.push([xyzw[3], xyzw[0], xyzw[1], xyzw[2]]);
    }
    flip_yz(&mut s);
    Ok(s)
}

/// Version 3+: the largest component's index in the top 2 bits, the other three as a sign
/// and 9-bit magnitude in [0, 1/√2], the last component in the lowest bits.
fn unpack_smallest_three(r: &[u8]) -> [f32; 4] {
    let mut comp = u32::from_le_bytes([r[0], r[1], r[2], r[3]]);
    let largest = (comp >> 30) as usize;
    let mask = (1u32 << 9) - 1;
    let mut q = [0.0f32; 4];
    let mut sum = 0.0;
    for i in (0..4).rev() {
        if i == largest {
            continue;
        }
        let mag = (comp & mask) as f32 / mask as f32 * std::f32::consts::FRAC_1_SQRT_2;
        q[i] = if (comp >> 9) & 1 == 1 { -mag } else { mag };
        sum += q[i] * q[i];
        comp >>= 10;
    }
    q[largest] = (1.0 - sum).max(0.0).sqrt();
    q
}

/// Version 2: x, y, z as bytes in [−1, 1], w ≥ 0 from unit length.
fn first_three(r: &[u8]) -> [f32; 4] {
    let xyz: [f32; 3] = std::array::from_fn(|a| r[a] as f32 / 127.5 - 1.0);
    let w = (1.0 - xyz.iter().map(|v| v * v).sum::<f32>()).max(0.0).sqrt();
    [xyz[0], xyz[1], xyz[2], w]
}

/// A quaternion normalised, with the index of its largest component made positive: what
/// every "smallest three" encoding (compressed PLY, .spz, SOG) stores.
pub fn largest_component(q: [f32; 4]) -> (usize, [f32; 4]) {
    let norm = q.iter().map(|v| v * v).sum::<f32>().sqrt().max(1e-12);
    let q = q.map(|v| v / norm);
    let largest = (0..4).max_by(|&a, &b| q[a].abs().total_cmp(&q[b].abs())).unwrap_or(0);
    (largest, if q[largest] < 0.0 { q.map(|v| -v) } else { q })
}

fn pack_smallest_three(xyzw: [f32; 4]) -> [u8; 4] {
    let (largest, q) = largest_component(xyzw);
    let mask = (1u32 << 9) - 1;
    let mut comp = largest as u32;
    for (i, v) in q.iter().enumerate() {
        if i == largest {
            continue;
        }
        let mag = ((mask as f32) * (v.abs() / std::f32::consts::FRAC_1_SQRT_2) + 0.5).min(mask as f32) as u32;
        comp = (comp << 10) | ((v < &0.0) as u32) << 9 | mag;
    }
    comp.to_le_bytes()
}

fn unorm8(v: f32) -> u8 {
    (v * 255.0).round().clamp(0.0, 255.0) as u8
}

/// `scene` as a version-4 `.spz` (12 fractional bits; zstd level 12).
pub fn write_spz(scene: &Scene, path: &Path) -> Result<()> {
    let what = path.display().to_string();
    let mut s = scene.clone();
    flip_yz(&mut s);
    let n = s.len();
    let coeffs = s.sh_coeffs();
    let bits = 12;
    let limit = (1i32 << 23) - 1;
    for (i, m) in s.means.iter().enumerate() {
        if m.iter().any(|v| (v * (1 << bits) as f32).abs() > limit as f32) {
            bail!("{what}: Gaussian {i} lies {m:?} from the origin, outside .spz's ±2048 range at 12 fractional bits");
        }
    }
    let mut streams: Vec<Vec<u8>> =
        vec![Vec::with_capacity(n * 9), Vec::new(), Vec::new(), Vec::new(), Vec::new(), Vec::new()];
    for i in 0..n {
        for v in s.means[i] {
            let fixed = (v * (1 << bits) as f32).round() as i32;
            streams[0].extend_from_slice(&fixed.to_le_bytes()[..3]);
        }
        streams[1].push(unorm8(sigmoid(s.opacities[i])));
        let sh = &s.sh[i * coeffs * 3..(i + 1) * coeffs * 3];
        for v in &sh[..3] {
            streams[2].push(unorm8(v * SPZ_COLOR_SCALE + 0.5));
        }
        for v in s.scales[i] {
            streams[3].push(((v + 10.0) * 16.0).round().clamp(0.0, 255.0) as u8);
        }
        let [w, x, y, z] = s.quats[i];
        streams[4].extend_from_slice(&pack_smallest_three([x, y, z, w]));
        for v in &sh[3..] {
            streams[5].push((v * 128.0 + 128.0).round().clamp(0.0, 255.0) as u8);
        }
    }
    let streams: Vec<Vec<u8>> = streams.into_iter().filter(|s| !s.is_empty()).collect();
    let mut compressed = Vec::new();
    for st in &streams {
        compressed.push(zstd::bulk::compress(st, 12).with_context(|| format!("{what}: zstd"))?);
    }
    let mut out = Vec::new();
    out.extend_from_slice(SPZ_MAGIC);
    out.extend_from_slice(&4u32.to_le_bytes());
    out.extend_from_slice(&(n as u32).to_le_bytes());
    out.extend_from_slice(&[s.sh_degree as u8, bits as u8, 0, streams.len() as u8]);
    out.extend_from_slice(&32u32.to_le_bytes());
    out.extend_from_slice(&[0u8; 12]);
    for (c, st) in compressed.iter().zip(&streams) {
        out.extend_from_slice(&(c.len() as u64).to_le_bytes());
        out.extend_from_slice(&(st.len() as u64).to_le_bytes());
    }
    for c in &compressed {
        out.extend_from_slice(c);
    }
    crate::util::write_atomic(path, |f| std::io::Write::write_all(f, &out))
}

// ---------------------------------------------------------------------------------------------
// .splat

/// Reads antimatter15's `.splat`: per Gaussian 32 bytes — position f32×3, linear scale f32×3,
/// colour and opacity u8×4 (colour = 0.5 + SH_C0·sh0), rotation u8×4 (w, x, y, z; v/255·2 − 1).
pub fn read_splat(what: &str, bytes: &[u8]) -> Result<Scene> {
    if bytes.is_empty() || bytes.len() % 32 != 0 {
        bail!("{what}: a .splat file holds 32-byte rows, but it is {} bytes long", bytes.len());
    }
    let mut s = Scene::default();
    for (i, row) in bytes.chunks_exact(32).enumerate() {
        let f = |k: usize| f32::from_le_bytes(row[k * 4..k * 4 + 4].try_into().expect("4 bytes"));
        s.means.push([f(0), f(1), f(2)]);
        let scale = [f(3), f(4), f(5)];
        if scale.iter().any(|&v| v.is_nan() || v < 0.0) {
            bail!("{what}: Gaussian {i} has a negative or NaN scale {scale:?}");
        }
        s.scales.push(scale.map(|v| v.max(1e-30).ln()));
        s.sh.extend(row[24..27].iter().map(|&b| (b as f32 / 255.0 - 0.5) / SH_C0));
        s.opacities.push(opacity_logit(row[27] as f32 / 255.0));
        s.quats.push(std::array::from_fn(|k| row[28 + k] as f32 / 255.0 * 2.0 - 1.0));
    }
    Ok(s)
}

/// `scene` as `.splat` (SH bands beyond sh0 are dropped; rotations normalised).
pub fn write_splat(scene: &Scene, path: &Path) -> Result<()> {
    let coeffs = scene.sh_coeffs();
    let mut out = Vec::with_capacity(scene.len() * 32);
    for i in 0..scene.len() {
        for v in scene.means[i] {
            out.extend_from_slice(&v.to_le_bytes());
        }
        for v in scene.scales[i] {
            out.extend_from_slice(&v.exp().to_le_bytes());
        }
        for c in 0..3 {
            out.push(unorm8(0.5 + SH_C0 * scene.sh[i * coeffs * 3 + c]));
        }
        out.push(unorm8(sigmoid(scene.opacities[i])));
        let q = scene.quats[i];
        let norm = q.iter().map(|v| v * v).sum::<f32>().sqrt().max(1e-12);
        for v in q {
            out.push(unorm8((v / norm + 1.0) * 0.5));
        }
    }
    crate::util::write_atomic(path, |f| std::io::Write::write_all(f, &out))
}

// ---------------------------------------------------------------------------------------------
// SOG (versions 1 and 2)

#[derive(serde::Deserialize)]
struct SogMeans {
    mins: [f32; 3],
    maxs: [f32; 3],
    files: [String; 2],
    /// Version 1: [count, 3].
    shape: Option<[usize; 2]>,
}

/// An attribute's table: version 2 a 256-entry `codebook`, version 1 per-channel `mins` and
/// `maxs` (bytes lerped between them).
#[derive(serde::Deserialize)]
struct SogTable {
    codebook: Option<Vec<f32>>,
    mins: Option<Vec<f32>>,
    maxs: Option<Vec<f32>>,
    files: Vec<String>,
}

#[derive(serde::Deserialize)]
struct SogFiles {
    files: Vec<String>,
}

/// Version 2: `count`, `bands`, `codebook`; version 1: scalar `mins`/`maxs`, bands from the
/// centroids image's width.
#[derive(serde::Deserialize)]
struct SogShN {
    count: Option<usize>,
    bands: Option<u32>,
    codebook: Option<Vec<f32>>,
    mins: Option<f32>,
    maxs: Option<f32>,
    files: [String; 2],
}

#[derive(serde::Deserialize)]
struct SogMeta {
    version: Option<u32>,
    count: Option<usize>,
    means: SogMeans,
    scales: SogTable,
    quats: SogFiles,
    sh0: SogTable,
    #[serde(rename = "shN")]
    sh_n: Option<SogShN>,
}

/// Decodes a byte of channel `c`: a codebook entry (version 2) or a lerp (version 1).
enum Lookup {
    Codebook(Vec<f32>),
    Lerp(Vec<f32>, Vec<f32>),
}

impl Lookup {
    fn new(what: &str, name: &str, t: &SogTable, v1: bool, channels: usize) -> Result<Lookup> {
        if v1 {
            match (&t.mins, &t.maxs) {
                (Some(lo), Some(hi)) if lo.len() >= channels && hi.len() >= channels => {
                    Ok(Lookup::Lerp(lo.clone(), hi.clone()))
                }
                _ => bail!("{what}: \"{name}\" needs {channels} mins and maxs (SOG version 1)"),
            }
        } else {
            match &t.codebook {
                Some(c) if c.len() == 256 => Ok(Lookup::Codebook(c.clone())),
                _ => bail!("{what}: \"{name}\" needs a 256-entry codebook (SOG version 2)"),
            }
        }
    }

    fn get(&self, c: usize, b: u8) -> f32 {
        match self {
            Lookup::Codebook(book) => book[b as usize],
            Lookup::Lerp(lo, hi) => lo[c] + (hi[c] - lo[c]) * (b as f32 / 255.0),
        }
    }
}

/// An RGBA image decoded from a SOG WebP file: (width, height, bytes).
fn sog_image(dir: &Path, name: &str, count: usize) -> Result<(usize, usize, Vec<u8>)> {
    let path = dir.join(name);
    let what = path.display();
    let bytes = std::fs::read(&path).with_context(|| format!("{what}: cannot read (named by meta.json)"))?;
    let img = image::load_from_memory_with_format(&bytes, image::ImageFormat::WebP)
        .map_err(|e| anyhow!("{what}: not a WebP image: {e}"))?
        .to_rgba8();
    let (w, h) = (img.width() as usize, img.height() as usize);
    if w * h < count {
        bail!("{what}: {w}×{h} texels cannot hold {count} Gaussians");
    }
    Ok((w, h, img.into_raw()))
}

/// Reads a SOG scene, version 2 or 1: `meta.json` (or its folder) and the WebP images it
/// names (splat-transform's layouts; version 1 lerps bytes between per-channel bounds where
/// version 2 has codebooks, and stores the opacity logit itself).
pub fn read_sog(path: &Path) -> Result<Scene> {
    let meta_path: PathBuf = if path.is_dir() { path.join("meta.json") } else { path.to_path_buf() };
    let what = meta_path.display().to_string();
    let dir = meta_path.parent().unwrap_or(Path::new("."));
    let text = std::fs::read_to_string(&meta_path).with_context(|| format!("{what}: cannot read"))?;
    let meta: SogMeta = serde_json::from_str(&text).map_err(|e| anyhow!("{what}: not a SOG meta.json: {e}"))?;
    let v1 = match meta.version {
        Some(2) => false,
        None => true,
        Some(v) => bail!("{what}: SOG version {v} is not read (versions 1 and 2 are)"),
    };
    let n = if v1 { meta.means.shape.map(|s| s[0]) } else { meta.count }
        .ok_or_else(|| anyhow!("{what}: no Gaussian count (\"count\", or version 1's \"means.shape\")"))?;
    if n == 0 {
        bail!("{what}: the SOG holds no Gaussians");
    }
    let scale_of = Lookup::new(&what, "scales", &meta.scales, v1, 3)?;
    let sh0_of = Lookup::new(&what, "sh0", &meta.sh0, v1, if v1 { 4 } else { 3 })?;
    let one =
        |c: &SogTable, name: &str| c.files.first().cloned().ok_or_else(|| anyhow!("{what}: \"{name}\" names no file"));
    let (_, _, lo) = sog_image(dir, &meta.means.files[0], n)?;
    let (_, _, hi) = sog_image(dir, &meta.means.files[1], n)?;
    let quat_file = meta.quats.files.first().ok_or_else(|| anyhow!("{what}: \"quats\" names no file"))?;
    let (_, _, quats) = sog_image(dir, quat_file, n)?;
    let (_, _, scales) = sog_image(dir, &one(&meta.scales, "scales")?, n)?;
    let (_, _, sh0) = sog_image(dir, &one(&meta.sh0, "sh0")?, n)?;
    // The SH palette: (coefficients, centroids image width, its bytes, labels, entries, lookup).
    let mut palette = None;
    let mut degree = 0;
    if let Some(sh) = &meta.sh_n {
        let centroids_path = dir.join(&sh.files[0]);
        let (cw, ch, centroids) = sog_image(dir, &sh.files[0], 0)?;
        let bands = if v1 {
            match cw {
                192 => 1,
                512 => 2,
                960 => 3,
                _ => {
                    bail!("{}: {cw} texels wide; SOG version 1 palettes are 192, 512 or 960", centroids_path.display())
                }
            }
        } else {
            sh.bands.unwrap_or(0)
        };
        if bands > 3 {
            bail!("{what}: shN with {bands} bands is not supported (1..3)");
        }
        if bands > 0 {
            let coeffs = ((bands + 1) * (bands + 1) - 1) as usize;
            if cw != 64 * coeffs {
                bail!("{}: {cw} texels wide; {bands} bands need {}", centroids_path.display(), 64 * coeffs);
            }
            let (count, lookup) = if v1 {
                let (Some(a), Some(b)) = (sh.mins, sh.maxs) else {
                    bail!("{what}: \"shN\" needs mins and maxs (SOG version 1)")
                };
                (ch * 64, Lookup::Lerp(vec![a; 3], vec![b; 3]))
            } else {
                match (&sh.codebook, sh.count) {
                    (Some(c), Some(count)) if c.len() == 256 => (count, Lookup::Codebook(c.clone())),
                    _ => bail!("{what}: \"shN\" needs a count and a 256-entry codebook (SOG version 2)"),
                }
            };
            if count > ch * 64 {
                bail!("{what}: shN count {count} exceeds its centroids image ({} entries)", ch * 64);
            }
            let (_, _, labels) = sog_image(dir, &sh.files[1], n)?;
            degree = bands;
            palette = Some((coeffs, cw, centroids, labels, count, lookup));
        }
    }
    let m = &meta.means;
    let mut s = Scene { sh_degree: degree, ..Default::default() };
    let unlog = |v: f32| v.signum() * (v.abs().exp() - 1.0);
    for i in 0..n {
        let o = i * 4;
        s.means.push(std::array::from_fn(|a| {
            let q = (lo[o + a] as u32 | (hi[o + a] as u32) << 8) as f32 / 65535.0;
            let range = if m.maxs[a] > m.mins[a] { m.maxs[a] - m.mins[a] } else { 1.0 };
            unlog(m.mins[a] + range * q)
        }));
        let tag = quats[o + 3];
        if !(252..=255).contains(&tag) {
            bail!("{what}: Gaussian {i}'s rotation tag {tag} is not 252-255");
        }
        let largest = (tag - 252) as usize;
        let abc = [0, 1, 2].map(|k| (quats[o + k] as f32 / 255.0 * 2.0 - 1.0) * std::f32::consts::FRAC_1_SQRT_2);
        let mut q = [0.0f32; 4];
        let mut k = 0;
        for (j, v) in q.iter_mut().enumerate() {
            if j != largest {
                *v = abc[k];
                k += 1;
            }
        }
        q[largest] = (1.0 - abc.iter().map(|v| v * v).sum::<f32>()).max(0.0).sqrt();
        s.quats.push(q);
        s.scales.push(std::array::from_fn(|a| scale_of.get(a, scales[o + a])));
        s.opacities.push(if v1 {
            // Version 1 stores the logit itself between its bounds.
            sh0_of.get(3, sh0[o + 3])
        } else {
            opacity_logit(sh0[o + 3] as f32 / 255.0)
        });
        for c in 0..3 {
            s.sh.push(sh0_of.get(c, sh0[o + c]));
        }
        if let Some((coeffs, cw, centroids, labels, count, lookup)) = &palette {
            let label = labels[o] as usize | (labels[o + 1] as usize) << 8;
            if label >= *count {
                bail!("{what}: Gaussian {i}'s SH palette label {label} is not below its count {count}");
            }
            let (row, col) = (label / 64, (label % 64) * coeffs);
            for j in 0..*coeffs {
                let t = (row * cw + col + j) * 4;
                for c in 0..3 {
                    s.sh.push(lookup.get(c, centroids[t + c]));
                }
            }
        }
    }
    Ok(s)
}

/// 1D k-means (Lloyd) of `values` into at most `k` centres, ascending.
fn codebook_1d(values: &[f32], k: usize) -> Vec<f32> {
    let mut v: Vec<f32> = values.to_vec();
    v.sort_by(f32::total_cmp);
    let n = v.len();
    if n == 0 {
        return vec![0.0; k];
    }
    // Half the starts at quantiles (where the values are), half evenly over the range (so
    // the rare extremes — the largest splats, the brightest colours — keep entries of their own).
    let (lo, hi) = (v[0], v[n - 1]);
    let mut centres: Vec<f32> = (0..k)
        .map(|i| {
            let t = (i / 2) as f64 / (k / 2).max(1) as f64 + 0.5 / k as f64;
            if i % 2 == 0 {
                v[((t * n as f64) as usize).min(n - 1)]
            } else {
                lo + (hi - lo) * t as f32
            }
        })
        .collect();
    centres.sort_by(f32::total_cmp);
    for _ in 0..10 {
        centres.dedup();
        // Sorted values: each centre's members are a run between the midpoints.
        let mut sums = vec![(0.0f64, 0usize); centres.len()];
        let mut c = 0;
        for &x in &v {
            while c + 1 < centres.len() && x > 0.5 * (centres[c] + centres[c + 1]) {
                c += 1;
            }
            sums[c].0 += x as f64;
            sums[c].1 += 1;
        }
        for (centre, (s, m)) in centres.iter_mut().zip(&sums) {
            if *m > 0 {
                *centre = (*s / *m as f64) as f32;
            }
        }
        centres.sort_by(f32::total_cmp);
    }
    centres.resize(k, *centres.last().unwrap_or(&0.0));
    centres
}

/// The index of the codebook entry nearest to `x` (the codebook ascending).
fn nearest(codebook: &[f32], x: f32) -> u8 {
    let i = codebook.partition_point(|&c| c < x);
    let best = match i {
        0 => 0,
        i if i >= codebook.len() => codebook.len() - 1,
        i => {
            if (x - codebook[i - 1]).abs() <= (codebook[i] - x).abs() {
                i - 1
            } else {
                i
            }
        }
    };
    best as u8
}

/// Entries of the SH palette (k-means centres of the Gaussians' shN vectors) at most.
pub const SOG_PALETTE: usize = 1024;

fn write_webp(path: &Path, w: usize, h: usize, rgba: &[u8]) -> Result<()> {
    let mut bytes = Vec::new();
    image::codecs::webp::WebPEncoder::new_lossless(&mut bytes)
        .encode(rgba, w as u32, h as u32, image::ExtendedColorType::Rgba8)
        .map_err(|e| anyhow!("{}: WebP: {e}", path.display()))?;
    crate::util::write_atomic(path, |f| std::io::Write::write_all(f, &bytes))
}

/// `scene` as SOG version 2: `meta.json` and lossless WebP images in the folder of `meta`
/// (created). Positions 16-bit in log space (splat-transform's sign(x)·ln(|x| + 1)), rotations
/// smallest-three 8-bit, scales and sh0 through 256-entry codebooks (1D k-means), opacity 8-bit,
/// SH bands as a palette of at most [`SOG_PALETTE`] k-means centres (10 Lloyd iterations) whose
/// coefficients go through a third codebook.
pub fn write_sog(scene: &Scene, meta: &Path) -> Result<()> {
    let dir = meta.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
    std::fs::create_dir_all(dir).with_context(|| format!("{}: cannot create", dir.display()))?;
    let n = scene.len();
    let coeffs = scene.sh_coeffs();
    let w = ((n as f64).sqrt().ceil() as usize).div_ceil(4) * 4;
    let h = n.div_ceil(w);
    let image = || vec![0u8; w * h * 4];
    let log = |x: f32| x.signum() * (x.abs() + 1.0).ln();
    let mut mins = [f32::MAX; 3];
    let mut maxs = [f32::MIN; 3];
    for m in &scene.means {
        for a in 0..3 {
            mins[a] = mins[a].min(log(m[a]));
            maxs[a] = maxs[a].max(log(m[a]));
        }
    }
    let (mut lo, mut hi, mut quats, mut scales, mut sh0) = (image(), image(), image(), image(), image());
    let scale_book = codebook_1d(&scene.scales.iter().flatten().copied().collect::<Vec<_>>(), 256);
    let dc: Vec<f32> = (0..n).flat_map(|i| scene.sh[i * coeffs * 3..i * coeffs * 3 + 3].to_vec()).collect();
    let sh0_book = codebook_1d(&dc, 256);
    for i in 0..n {
        let o = i * 4;
        for a in 0..3 {
            let range = if maxs[a] > mins[a] { maxs[a] - mins[a] } else { 1.0 };
            let q = (((log(scene.means[i][a]) - mins[a]) / range * 65535.0).round().clamp(0.0, 65535.0)) as u32;
            lo[o + a] = (q & 255) as u8;
            hi[o + a] = (q >> 8) as u8;
            scales[o + a] = nearest(&scale_book, scene.scales[i][a]);
            sh0[o + a] = nearest(&sh0_book, dc[i * 3 + a]);
        }
        lo[o + 3] = 255;
        hi[o + 3] = 255;
        scales[o + 3] = 255;
        sh0[o + 3] = unorm8(sigmoid(scene.opacities[i]));
        let (largest, q) = largest_component(scene.quats[i]);
        let mut k = 0;
        for (j, v) in q.iter().enumerate() {
            if j != largest {
                quats[o + k] = unorm8((v * std::f32::consts::SQRT_2 + 1.0) * 0.5);
                k += 1;
            }
        }
        quats[o + 3] = 252 + largest as u8;
    }
    let names = ["means_l.webp", "means_u.webp", "quats.webp", "scales.webp", "sh0.webp"];
    for (name, img) in names.iter().zip([&lo, &hi, &quats, &scales, &sh0]) {
        write_webp(&dir.join(name), w, h, img)?;
    }
    let mut doc = serde_json::json!({
        "version": 2,
        "asset": {"generator": "instgs-vk"},
        "count": n,
        "means": {"mins": mins, "maxs": maxs, "files": [names[0], names[1]]},
        "scales": {"codebook": scale_book, "files": [names[3]]},
        "quats": {"files": [names[2]]},
        "sh0": {"codebook": sh0_book, "files": [names[4]]},
    });
    if coeffs > 1 {
        let rest = (coeffs - 1) * 3;
        let vectors: Vec<&[f32]> = (0..n).map(|i| &scene.sh[i * coeffs * 3 + 3..(i + 1) * coeffs * 3]).collect();
        let (centres, labels) = palette(&vectors, rest, SOG_PALETTE.min(n));
        let book = codebook_1d(&centres, 256);
        let count = centres.len() / rest;
        let (cw, ch) = (64 * (coeffs - 1), count.div_ceil(64));
        let mut cimg = vec![0u8; cw * ch * 4];
        for c in 0..count {
            for j in 0..coeffs - 1 {
                let t = ((c / 64) * cw + (c % 64) * (coeffs - 1) + j) * 4;
                for ch in 0..3 {
                    // Centres are stored coefficient-major then RGB, as the Gaussians' sh.
                    cimg[t + ch] = nearest(&book, centres[c * rest + j * 3 + ch]);
                }
                cimg[t + 3] = 255;
            }
        }
        let mut limg = image();
        for (i, &l) in labels.iter().enumerate() {
            limg[i * 4] = (l & 255) as u8;
            limg[i * 4 + 1] = (l >> 8) as u8;
            limg[i * 4 + 3] = 255;
        }
        write_webp(&dir.join("shN_centroids.webp"), cw, ch, &cimg)?;
        write_webp(&dir.join("shN_labels.webp"), w, h, &limg)?;
        doc["shN"] = serde_json::json!({
            "count": count, "bands": scene.sh_degree, "codebook": book,
            "files": ["shN_centroids.webp", "shN_labels.webp"],
        });
    }
    let text = serde_json::to_string(&doc)?;
    crate::util::write_atomic(meta, |f| std::io::Write::write_all(f, text.as_bytes()))
}

/// k-means of `vectors` (each `dim` long) into `k` centres: evenly spaced starts, 10 Lloyd
/// iterations, brute-force assignment. Returns the centres (flat) and each vector's label.
fn palette(vectors: &[&[f32]], dim: usize, k: usize) -> (Vec<f32>, Vec<u32>) {
    let n = vectors.len();
    let mut centres: Vec<f32> = (0..k).flat_map(|c| vectors[c * n / k].to_vec()).collect();
    let mut labels = vec![0u32; n];
    for _ in 0..10 {
        for (i, v) in vectors.iter().enumerate() {
            let mut best = (f32::MAX, 0);
            for c in 0..k {
                let d: f32 = centres[c * dim..(c + 1) * dim].iter().zip(*v).map(|(a, b)| (a - b) * (a - b)).sum();
                if d < best.0 {
                    best = (d, c);
                }
            }
            labels[i] = best.1 as u32;
        }
        let mut sums = vec![0.0f64; k * dim];
        let mut counts = vec![0usize; k];
        for (v, &l) in vectors.iter().zip(&labels) {
            counts[l as usize] += 1;
            for (s, x) in sums[l as usize * dim..(l as usize + 1) * dim].iter_mut().zip(*v) {
                *s += *x as f64;
            }
        }
        for c in 0..k {
            if counts[c] > 0 {
                for d in 0..dim {
                    centres[c * dim + d] = (sums[c * dim + d] / counts[c] as f64) as f32;
                }
            }
        }
    }
    (centres, labels)
}

/// `instgs-vk convert`: `path` (any readable scene) to `out`, the format chosen by `out`'s name
/// ([`write_scene`]); an instanced scene to `.json` writes its scene graph.
pub fn convert(path: &Path, out: &Path) -> Result<()> {
    let scene = crate::formats::instgs::AnyScene::read(path)?;
    let name = out.file_name().map(|n| n.to_string_lossy().to_ascii_lowercase()).unwrap_or_default();
    match (&scene, name.ends_with(".json") && !name.ends_with("meta.json")) {
        (crate::formats::instgs::AnyScene::Instanced(s), true) => {
            let text = serde_json::to_string_pretty(&crate::model::instanced::scene_graph(s))?;
            crate::util::write_atomic(out, |f| {
                use std::io::Write;
                f.write_all(text.as_bytes())
            })?;
        }
        (crate::formats::instgs::AnyScene::Plain(_), true) => {
            bail!("{}: a scene graph (.json) comes from an instanced scene; {} is plain", out.display(), path.display())
        }
        (crate::formats::instgs::AnyScene::Plain(s), false) => crate::formats::write_scene(s, out)?,
        (crate::formats::instgs::AnyScene::Instanced(s), false) => crate::formats::write_scene(&s.expand(), out)?,
    }
    eprintln!("wrote {}", out.display());
    Ok(())
}
