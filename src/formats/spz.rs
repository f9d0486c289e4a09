//! Niantic `.spz`: versions 2 and 3 (gzip) and 4 (zstd streams with a table of contents) read;
//! version 4 written. Its frame (x right, y up, z back) is turned into the PLY frame on reading.
use std::io::Read;
use std::path::Path;

use anyhow::{anyhow, bail, Context, Result};

use crate::formats::quant::{largest_component, opacity_logit, unorm8};
use crate::math::sigmoid;
use crate::model::scene::Scene;

/// Sign of SH coefficient k (1..16, band-major, m = −l..l as Inria orders them) when y and z
/// are negated: the parity of its basis function in y and z.
const SH_FLIP_YZ: [f32; 16] = [1.0, -1.0, -1.0, 1.0, -1.0, 1.0, 1.0, -1.0, 1.0, -1.0, 1.0, -1.0, -1.0, 1.0, -1.0, 1.0];

/// How `.spz` files are framed (the command line's `--spz-frame`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum SpzFrame {
    /// Niantic's specification: x right, y up, z back (turned into the PLY frame and back).
    Spec,
    /// No axis change: the PLY frame as stored (splat-transform's reading and writing).
    AsStored,
}

static AS_STORED: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(false);

/// Sets how every later `.spz` read or write is framed (process-wide; default [`SpzFrame::Spec`]).
pub fn set_frame(frame: SpzFrame) {
    AS_STORED.store(frame == SpzFrame::AsStored, std::sync::atomic::Ordering::Relaxed);
}

/// Negates y and z of the whole scene (the `.spz` frame ↔ the PLY frame; its own inverse),
/// unless the frame is [`SpzFrame::AsStored`].
fn flip_yz(s: &mut Scene) {
    if !AS_STORED.load(std::sync::atomic::Ordering::Relaxed) {
        negate_yz(s);
    }
}

/// Negates y and z of the whole scene: means, rotations and SH (a half turn about x).
fn negate_yz(s: &mut Scene) {
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

/// Reads a `.spz` file's bytes (versions 2-3 gzip-compressed, 4 with zstd streams), framed as
/// [`set_frame`] says.
pub fn read_spz(what: &str, bytes: &[u8]) -> Result<Scene> {
    let mut s = read_spz_stored(what, bytes, None)?;
    flip_yz(&mut s);
    Ok(s)
}

/// SPZ bytes inside glTF (`KHR_gaussian_splatting_compression_spz_2`), in glTF's frame as
/// stored: CesiumJS, the extension's implementation, unpacks them without an axis change
/// ([`spz_in_gltf`] says why). Refused unless it holds `count` Gaussians (its accessors'
/// count; checked before decoding).
pub fn read_spz_in_gltf(what: &str, bytes: &[u8], count: usize) -> Result<Scene> {
    read_spz_stored(what, bytes, Some(count))
}

/// A `.spz` file's Gaussians as stored (no axis change); refused before decoding when its
/// header's count is not `expected`.
fn read_spz_stored(what: &str, bytes: &[u8], expected: Option<usize>) -> Result<Scene> {
    let check_count = |h: &SpzHeader| match expected {
        Some(n) if n != h.count => bail!("{what}: the SPZ data holds {} Gaussians, its accessors say {n}", h.count),
        _ => Ok(()),
    };
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
        check_count(&h)?;
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
        // The streams are laid end to end, each count × stride bytes: more data than the
        // header's count needs means the count is wrong, and every stream after the first
        // would be read from the wrong place.
        let mut extra = [0u8; 1];
        if gz.read(&mut extra).map_err(|e| anyhow!("{what}: corrupt gzip stream: {e}"))? > 0 {
            let more = 1 + std::io::copy(&mut gz, &mut std::io::sink()).unwrap_or(0);
            bail!(
                "{what}: the decompressed data holds {more} bytes more than the header's {} Gaussians need: the count is wrong",
                h.count
            );
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
    check_count(&h)?;
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

/// `scene` as a version-4 `.spz` (12 fractional bits; zstd level 12), framed as [`set_frame`]
/// says.
pub fn write_spz(scene: &Scene, path: &Path) -> Result<()> {
    let what = path.display().to_string();
    scene.validate(&format!("{what}: not written"))?;
    let mut s = scene.clone();
    flip_yz(&mut s);
    let out = encode(&s, &what, 4)?;
    crate::util::write_atomic(path, |f| std::io::Write::write_all(f, &out))
}

/// `scene`, in glTF's frame, as the SPZ bytes `KHR_gaussian_splatting_compression_spz_2`
/// holds: a version-3 `.spz` (gzip, rotations as smallest three: what Niantic's library
/// writes; version 2's three 8-bit components err by up to 0.09 where w is small) with glTF's
/// axes stored as they are. The extension's text asks writers to pack from
/// glTF's frame into SPZ's own (x right, y up, z back: a half turn about y), but CesiumJS
/// 1.145 unpacks with no conversion (`coordinateSystem: "UNSPECIFIED"`), so data packed that
/// way draws turned (glTF issue #2509); we store what Cesium draws right, and read it the same
/// way ([`read_spz_in_gltf`]).
pub fn spz_in_gltf(scene: &Scene, what: &str) -> Result<Vec<u8>> {
    scene.validate(&format!("{what}: not written"))?;
    encode(scene, what, 3)
}

/// `s` (already in the frame to store) as `.spz` bytes: version 4 (zstd streams with a table of
/// contents) or 3 (one gzip stream); rotations as smallest three; 12 fractional bits.
fn encode(s: &Scene, what: &str, version: u32) -> Result<Vec<u8>> {
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
    let mut out = Vec::new();
    if version < 4 {
        let mut body = Vec::new();
        body.extend_from_slice(SPZ_MAGIC);
        body.extend_from_slice(&version.to_le_bytes());
        body.extend_from_slice(&(n as u32).to_le_bytes());
        body.extend_from_slice(&[s.sh_degree as u8, bits as u8, 0, 0]);
        for st in &streams {
            body.extend_from_slice(st);
        }
        let mut gz = flate2::write::GzEncoder::new(&mut out, flate2::Compression::best());
        std::io::Write::write_all(&mut gz, &body).with_context(|| format!("{what}: gzip"))?;
        gz.finish().with_context(|| format!("{what}: gzip"))?;
        return Ok(out);
    }
    let streams: Vec<Vec<u8>> = streams.into_iter().filter(|s| !s.is_empty()).collect();
    let mut compressed = Vec::new();
    for st in &streams {
        compressed.push(zstd::bulk::compress(st, 12).with_context(|| format!("{what}: zstd"))?);
    }
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
    Ok(out)
}
