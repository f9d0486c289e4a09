//! The `.instgs` file: one instanced scene in one file (format described in
//! `docs/format.md`).
//!
//! ```text
//! 0   8 bytes   magic "INSTGS\0\0"
//! 8   u32 LE    header length H
//! 12  H bytes   JSON header (UTF-8)
//!     padding   zeros up to the next multiple of 16: the data start D
//! D   sections  little-endian arrays at header-declared offsets relative to D
//! end−4  u32 LE  (version 2) CRC-32 (IEEE) of every byte before it
//! ```
//! Version 1 files (no checksum) still read. Version 3 is version 2 with the Gaussian
//! parameters of each part (background, templates) as one SOG bundle (header `param_dtype`
//! "sog"). Version 4 ([`write_compressed`]) holds the background's and every template's
//! Gaussians as one SOG bundle, and may store the offsets as `q8` (`crate::formats::q8`).
use std::io::Write;
use std::path::Path;

use anyhow::{anyhow, bail, Context, Result};
use half::f16;
use serde::{Deserialize, Serialize};

use crate::model::instanced::{mat4_from_rows, mat4_to_rows, Group, Instance, InstancedScene, Offsets, Similarity};
use crate::model::scene::Scene;

pub const MAGIC: &[u8; 8] = b"INSTGS\0\0";
pub const VERSION: u32 = 2;
/// The version of files whose Gaussian parameters are a SOG bundle per part (read only).
pub const VERSION_SOG: u32 = 3;
/// The version of files whose Gaussian parameters are one SOG bundle, or whose offsets are `q8`.
pub const VERSION_PACKED: u32 = 4;
/// Headers larger than this are refused (a corrupt length would otherwise allocate gigabytes).
const MAX_HEADER: usize = 64 << 20;

/// Storage of the offsets (header `offset_dtype`: f32, f16, pq8 or q8) and type of a section
/// (f32, f16, u8, sog or zstd).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Dtype {
    F32,
    F16,
    /// Section type: bytes.
    U8,
    /// Offset storage: product-quantised (`crate::formats::pq8`): sections `d_codes` (u8, [K, T, 2]),
    /// `d_codebook_dp` (f32, [256, 3]) and `d_codebook_dc` (f32, [256, 4]).
    Pq8,
    /// Offset storage: signed 8-bit multiples of a step per kind (`crate::formats::q8`):
    /// sections `d_steps` (f32, shape `[3]`) and `d_codes` (zstd, shape `[bytes]`).
    Q8,
    /// Section type: a zstd frame's bytes, shape `[bytes]`.
    Zstd,
    /// Parameter storage (header `param_dtype`) and section type: a part's Gaussians as one SOG
    /// bundle (`crate::formats::sog`: a zip of `meta.json` and WebP images), section `sog` of
    /// shape `[bytes]`; empty for a part without Gaussians. Version 4: one bundle, section
    /// `gaussians/sog`, the background's Gaussians then each group's template's.
    Sog,
}

impl Dtype {
    /// An offset storage by its configuration name ("f32", "f16" or "pq8"; q8 is a file's
    /// storage only, written by [`write_compressed`]).
    pub fn offsets(name: &str) -> Result<Dtype> {
        match name {
            "f32" => Ok(Dtype::F32),
            "f16" => Ok(Dtype::F16),
            "pq8" => Ok(Dtype::Pq8),
            _ => bail!("offset storage must be \"f32\", \"f16\" or \"pq8\", not {name:?}"),
        }
    }

    fn size(self) -> usize {
        match self {
            Dtype::F32 => 4,
            Dtype::F16 => 2,
            Dtype::U8 | Dtype::Pq8 | Dtype::Q8 | Dtype::Zstd | Dtype::Sog => 1,
        }
    }
}

/// Product-quantised offset sections: name suffix, type, shape tail after [K, T] or [256].
const CODE_SECTIONS: [(&str, Dtype); 3] =
    [("d_codes", Dtype::U8), ("d_codebook_dp", Dtype::F32), ("d_codebook_dc", Dtype::F32)];

#[derive(Serialize, Deserialize)]
struct Header {
    format: String,
    version: u32,
    sh_degree: u32,
    background_gaussians: usize,
    offset_dtype: Dtype,
    /// f32 (absent: five f32 sections per part) or sog (version 3: a bundle per part; 4: one).
    #[serde(default = "f32_params", skip_serializing_if = "is_f32")]
    param_dtype: Dtype,
    groups: Vec<GroupHeader>,
    sections: Vec<Section>,
}

#[derive(Serialize, Deserialize)]
struct GroupHeader {
    name: String,
    template_gaussians: usize,
    instances: Vec<InstanceHeader>,
}

#[derive(Serialize, Deserialize)]
struct InstanceHeader {
    id: String,
    /// Template → world, 4×4 row-major (column vectors).
    transform: [[f32; 4]; 4],
}

#[derive(Serialize, Deserialize, Clone)]
struct Section {
    name: String,
    dtype: Dtype,
    shape: Vec<usize>,
    /// Bytes from the data start.
    offset: u64,
    bytes: u64,
}

/// How a file stores an instanced scene: its offsets (f32, f16, pq8) and its Gaussian
/// parameters (f32, sog).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Storage {
    pub offsets: Dtype,
    pub params: Dtype,
}

impl Storage {
    /// f32 throughout: lossless.
    pub const F32: Storage = Storage { offsets: Dtype::F32, params: Dtype::F32 };
    /// [`write_compressed`]'s.
    pub const COMPRESSED: Storage = Storage { offsets: Dtype::Q8, params: Dtype::Sog };

    /// Offsets stored as `offsets`, parameters as f32.
    pub fn offsets(offsets: Dtype) -> Storage {
        Storage { offsets, params: Dtype::F32 }
    }
}

fn f32_params() -> Dtype {
    Dtype::F32
}

fn is_f32(d: &Dtype) -> bool {
    *d == Dtype::F32
}

/// Bytes of one part of a file, as `info` reports them.
#[derive(Clone, Debug, Serialize)]
pub struct PartBytes {
    pub name: String,
    pub bytes: u64,
}

/// The sections of a Gaussian part (`background` or `group/<index>`): name suffix, shape tail.
fn gauss_sections(sh_coeffs: usize) -> [(&'static str, Vec<usize>); 5] {
    [("means", vec![3]), ("scales", vec![3]), ("quats", vec![4]), ("opacities", vec![]), ("sh", vec![sh_coeffs, 3])]
}

/// Version 4's one SOG bundle of every part's Gaussians.
const PACKED_SECTION: &str = "gaussians/sog";

const OFFSET_SECTIONS: [(&str, usize); 3] = [("d_means", 3), ("d_sh0", 3), ("d_opacities", 1)];

fn f32_bytes(v: &[f32], dtype: Dtype) -> Vec<u8> {
    match dtype {
        Dtype::F32 => v.iter().flat_map(|x| x.to_le_bytes()).collect(),
        Dtype::F16 => v.iter().flat_map(|x| f16::from_f32(*x).to_le_bytes()).collect(),
        Dtype::U8 | Dtype::Pq8 | Dtype::Q8 | Dtype::Zstd | Dtype::Sog => v.iter().map(|&x| x as u8).collect(),
    }
}

fn scene_arrays(s: &Scene) -> [Vec<f32>; 5] {
    [s.means.concat(), s.scales.concat(), s.quats.concat(), s.opacities.clone(), s.sh.clone()]
}

/// Serialises `scene` (offsets stored as `offset_dtype`, parameters as f32).
pub fn to_bytes(scene: &InstancedScene, offset_dtype: Dtype) -> Vec<u8> {
    to_bytes_stored(scene, Storage::offsets(offset_dtype)).expect("f32 parameters serialise")
}

/// Serialises `scene` as `storage` says (parameters f32, or sog: one SOG bundle of the
/// background's and the templates' Gaussians, lossy as SOG is).
pub fn to_bytes_stored(scene: &InstancedScene, storage: Storage) -> Result<Vec<u8>> {
    let Storage { offsets: offset_dtype, params } = storage;
    if ![Dtype::F32, Dtype::Sog].contains(&params) {
        bail!("parameters are stored as f32 or sog, not {params:?}");
    }
    let coeffs = ((scene.sh_degree + 1) * (scene.sh_degree + 1)) as usize;
    let mut sections = Vec::new();
    let mut data: Vec<u8> = Vec::new();
    let mut push = |name: String, dtype: Dtype, shape: Vec<usize>, bytes: Vec<u8>, data: &mut Vec<u8>| {
        sections.push(Section { name, dtype, shape, offset: data.len() as u64, bytes: bytes.len() as u64 });
        data.extend_from_slice(&bytes);
        while !data.len().is_multiple_of(16) {
            data.push(0);
        }
    };
    let mut parts: Vec<(String, &Scene)> = vec![("background".into(), &scene.background)];
    parts.extend(scene.groups.iter().enumerate().map(|(i, g)| (format!("group/{i}"), &g.template)));
    if params == Dtype::Sog {
        // One bundle: its codebooks, SH palette and images serve every part (a bundle per
        // template paid a palette entry per Gaussian).
        // Its k-means count a template's Gaussian once per instance, as it is drawn.
        let mut all = Scene { sh_degree: scene.sh_degree, ..scene.background.clone() };
        let mut weights = vec![1.0f32; all.len()];
        for g in &scene.groups {
            all.append(&g.template);
            weights.resize(all.len(), g.instances.len().max(1) as f32);
        }
        let bundle = if all.is_empty() { Vec::new() } else { crate::formats::sog::bundle_bytes(&all, Some(&weights))? };
        push(PACKED_SECTION.into(), Dtype::Sog, vec![bundle.len()], bundle, &mut data);
        parts.clear();
    }
    for (part, s) in &parts {
        for ((suffix, tail), arr) in gauss_sections(coeffs).into_iter().zip(scene_arrays(s)) {
            let shape = [vec![s.len()], tail].concat();
            push(format!("{part}/{suffix}"), Dtype::F32, shape, f32_bytes(&arr, Dtype::F32), &mut data);
        }
    }
    for (i, g) in scene.groups.iter().enumerate() {
        let (k, t) = (g.instances.len(), g.template.len());
        if offset_dtype == Dtype::Pq8 {
            let c = crate::formats::pq8::OffsetCodes::encode(&g.offsets, i as u64);
            let n = crate::formats::pq8::CODES;
            push(format!("group/{i}/d_codes"), Dtype::U8, vec![k, t, 2], c.codes.concat(), &mut data);
            push(
                format!("group/{i}/d_codebook_dp"),
                Dtype::F32,
                vec![n, 3],
                f32_bytes(&c.dp.concat(), Dtype::F32),
                &mut data,
            );
            push(
                format!("group/{i}/d_codebook_dc"),
                Dtype::F32,
                vec![n, 4],
                f32_bytes(&c.dc.concat(), Dtype::F32),
                &mut data,
            );
            continue;
        }
        if offset_dtype == Dtype::Q8 {
            let q = crate::formats::q8::OffsetCodes::encode(&g.offsets)?;
            push(format!("group/{i}/d_steps"), Dtype::F32, vec![3], f32_bytes(&q.steps, Dtype::F32), &mut data);
            push(format!("group/{i}/d_codes"), Dtype::Zstd, vec![q.codes.len()], q.codes, &mut data);
            continue;
        }
        if ![Dtype::F32, Dtype::F16].contains(&offset_dtype) {
            bail!("offsets are stored as f32, f16, pq8 or q8, not {offset_dtype:?}");
        }
        let arrays = [g.offsets.d_means.concat(), g.offsets.d_sh0.concat(), g.offsets.d_opacities.clone()];
        for ((suffix, width), arr) in OFFSET_SECTIONS.into_iter().zip(arrays) {
            let shape = if width == 1 { vec![k, t] } else { vec![k, t, width] };
            push(format!("group/{i}/{suffix}"), offset_dtype, shape, f32_bytes(&arr, offset_dtype), &mut data);
        }
    }
    let header = Header {
        format: "instgs".into(),
        version: if params == Dtype::Sog || offset_dtype == Dtype::Q8 { VERSION_PACKED } else { VERSION },
        sh_degree: scene.sh_degree,
        background_gaussians: scene.background.len(),
        offset_dtype,
        param_dtype: params,
        groups: scene
            .groups
            .iter()
            .map(|g| GroupHeader {
                name: g.name.clone(),
                template_gaussians: g.template.len(),
                instances: g
                    .instances
                    .iter()
                    .map(|i| InstanceHeader { id: i.id.clone(), transform: mat4_to_rows(i.transform.to_mat4()) })
                    .collect(),
            })
            .collect(),
        sections,
    };
    let json = serde_json::to_vec(&header).expect("header serialises");
    let mut out = Vec::with_capacity(data.len() + json.len() + 32);
    out.extend_from_slice(MAGIC);
    out.extend_from_slice(&(json.len() as u32).to_le_bytes());
    out.extend_from_slice(&json);
    while out.len() % 16 != 0 {
        out.push(0);
    }
    out.extend_from_slice(&data);
    let crc = crc32fast::hash(&out);
    out.extend_from_slice(&crc.to_le_bytes());
    Ok(out)
}

/// Writes `scene` to `path` atomically. Refused, writing nothing, when the file would not read
/// back: offsets beyond f16's range (±65504) stored as f16 would be infinite.
pub fn write(scene: &InstancedScene, path: &Path, offset_dtype: Dtype) -> Result<()> {
    write_stored(scene, path, Storage::offsets(offset_dtype))
}

/// A compressed file: the Gaussian parameters of the background and of every template as one
/// SOG bundle (16-bit positions, 8-bit quaternions and opacities, codebooks for scales, colours
/// and SH) and the offsets as `q8` (each value an 8-bit multiple of its kind's step, the codes
/// zstd-compressed; pq8's two codes per pair would be smaller still, but cost cafe40's held-out
/// views 1 dB). Lossy; read back as any `.instgs`.
pub fn write_compressed(scene: &InstancedScene, path: &Path) -> Result<()> {
    write_stored(scene, path, Storage::COMPRESSED)
}

/// [`write()`] as `storage` says.
pub fn write_stored(scene: &InstancedScene, path: &Path, storage: Storage) -> Result<()> {
    let offset_dtype = storage.offsets;
    let what = path.display().to_string();
    scene.validate(&what)?;
    if offset_dtype == Dtype::F16 {
        let o = scene.groups.iter().map(|g| &g.offsets);
        let largest = o
            .flat_map(|o| o.d_means.iter().flatten().chain(o.d_sh0.iter().flatten()).chain(&o.d_opacities))
            .fold(0.0f32, |m, v| m.max(v.abs()));
        if largest > f16::MAX.to_f32() {
            bail!("{what}: not written: an offset of magnitude {largest} does not fit f16 (±65504); store the offsets as f32");
        }
    }
    let bytes = to_bytes_stored(scene, storage).with_context(|| format!("{what}: not written"))?;
    from_bytes(&bytes, &what).context("not written: the file would not read back")?;
    crate::util::write_atomic(path, |f| f.write_all(&bytes))
}

/// Header and data start of a file's bytes.
fn split(bytes: &[u8]) -> Result<(Header, &[u8], u64)> {
    if bytes.len() < 8 || &bytes[..8] != MAGIC {
        bail!("not an .instgs file (no INSTGS magic)");
    }
    if bytes.len() < 12 {
        bail!("cut short: {} bytes, not even the header length after the magic", bytes.len());
    }
    let len = u32::from_le_bytes(bytes[8..12].try_into().unwrap()) as usize;
    if len > MAX_HEADER || 12 + len > bytes.len() {
        bail!("header length {len} runs past the end of the file ({} bytes)", bytes.len());
    }
    let value: serde_json::Value =
        serde_json::from_slice(&bytes[12..12 + len]).map_err(|e| anyhow!("malformed JSON header: {e}"))?;
    if value.get("format").and_then(|f| f.as_str()) != Some("instgs") {
        bail!("header: format is not \"instgs\"");
    }
    let end = match value.get("version").and_then(|v| v.as_u64()) {
        Some(1) => bytes.len(),
        Some(v) if (VERSION as u64..=VERSION_PACKED as u64).contains(&v) => {
            let body = bytes
                .len()
                .checked_sub(4)
                .filter(|&b| b >= 12 + len)
                .ok_or_else(|| anyhow!("cut short: no checksum"))?;
            let stored = u32::from_le_bytes(bytes[body..].try_into().unwrap());
            if crc32fast::hash(&bytes[..body]) != stored {
                bail!("damaged: its checksum does not match its contents (a byte changed after it was written); write it again from its source");
            }
            body
        }
        Some(v) => bail!("header: version {v} is not supported (this build reads versions 1 to {VERSION_PACKED})"),
        None => bail!("header: no version"),
    };
    let header: Header = serde_json::from_value(value).map_err(|e| anyhow!("header: {e}"))?;
    let start = (12 + len).div_ceil(16) * 16;
    let data = bytes.get(start..end).unwrap_or(&[]);
    Ok((header, data, start as u64))
}

struct Sections<'a> {
    list: Vec<Section>,
    data: &'a [u8],
}

impl Sections<'_> {
    /// The values of section `name`, which must have `shape`.
    fn get(&self, name: &str, shape: &[usize], dtype: Dtype) -> Result<Vec<f32>> {
        let raw = self.raw(name, shape, dtype)?;
        Ok(match dtype {
            Dtype::F32 => raw.chunks_exact(4).map(|c| f32::from_le_bytes(c.try_into().unwrap())).collect(),
            Dtype::F16 => raw.chunks_exact(2).map(|c| f16::from_le_bytes(c.try_into().unwrap()).to_f32()).collect(),
            Dtype::U8 | Dtype::Pq8 | Dtype::Q8 | Dtype::Zstd | Dtype::Sog => raw.iter().map(|&b| b as f32).collect(),
        })
    }

    /// The bytes of section `name`, which must have `shape` and `dtype`.
    fn raw(&self, name: &str, shape: &[usize], dtype: Dtype) -> Result<&[u8]> {
        let mut found = self.list.iter().filter(|s| s.name == name);
        let s = found.next().ok_or_else(|| anyhow!("section {name:?} is missing"))?;
        if found.next().is_some() {
            bail!("section {name:?} appears twice");
        }
        if s.shape != shape {
            bail!("section {name:?} has shape {:?}; the header's counts need {shape:?}", s.shape);
        }
        if s.dtype != dtype {
            bail!("section {name:?} is {:?}, expected {dtype:?}", s.dtype);
        }
        let count = shape.iter().try_fold(1usize, |a, &b| a.checked_mul(b));
        let need =
            count.and_then(|c| c.checked_mul(dtype.size())).ok_or_else(|| anyhow!("section {name:?} too large"))?;
        if s.bytes != need as u64 {
            bail!("section {name:?} holds {} bytes; its shape needs {need}", s.bytes);
        }
        let end = s.offset.checked_add(s.bytes).filter(|&e| e <= self.data.len() as u64);
        let Some(end) = end else {
            bail!(
                "section {name:?} (offset {}, {} bytes) runs past the end of the data ({} bytes)",
                s.offset,
                s.bytes,
                self.data.len()
            );
        };
        Ok(&self.data[s.offset as usize..end as usize])
    }

    /// The bytes of section `name`, of shape `[bytes]` and type `dtype`.
    fn blob(&self, name: &str, dtype: Dtype) -> Result<&[u8]> {
        let s = self.list.iter().find(|s| s.name == name).ok_or_else(|| anyhow!("section {name:?} is missing"))?;
        self.raw(name, &[s.bytes as usize], dtype)
    }

    /// The `n` Gaussians of `part` (`gaussians`: all of them, version 4), stored as `params`.
    fn scene(&self, part: &str, n: usize, sh_degree: u32, params: Dtype) -> Result<Scene> {
        if params == Dtype::Sog {
            let name = format!("{part}/sog");
            let raw = self.blob(&name, Dtype::Sog)?;
            if n == 0 {
                if !raw.is_empty() {
                    bail!("section {name:?} holds {} bytes for no Gaussians", raw.len());
                }
                return Ok(Scene { sh_degree, ..Scene::default() });
            }
            let scene = crate::formats::sog::sog_from_bundle(raw, &format!("section {name:?}"))?;
            if scene.len() != n || scene.sh_degree != sh_degree {
                bail!(
                    "section {name:?} holds {} Gaussians of SH degree {}; the header says {n} of degree {sh_degree}",
                    scene.len(),
                    scene.sh_degree
                );
            }
            return Ok(scene);
        }
        if params != Dtype::F32 {
            bail!("header: param_dtype {params:?} is not a parameter storage (f32, sog)");
        }
        let coeffs = ((sh_degree + 1) * (sh_degree + 1)) as usize;
        let mut arrays = Vec::new();
        for (suffix, tail) in gauss_sections(coeffs) {
            arrays.push(self.get(&format!("{part}/{suffix}"), &[vec![n], tail].concat(), Dtype::F32)?);
        }
        let v3 = |a: &[f32]| a.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect();
        Ok(Scene {
            means: v3(&arrays[0]),
            scales: v3(&arrays[1]),
            quats: arrays[2].chunks_exact(4).map(|c| [c[0], c[1], c[2], c[3]]).collect(),
            opacities: std::mem::take(&mut arrays[3]),
            sh: std::mem::take(&mut arrays[4]),
            sh_degree,
        })
    }
}

/// Parses an `.instgs` file's bytes; `what` names it in errors.
pub fn from_bytes(bytes: &[u8], what: &str) -> Result<InstancedScene> {
    let (h, data, _) = split(bytes).with_context(|| what.to_string())?;
    let parse = || -> Result<InstancedScene> {
        if h.sh_degree > 3 {
            bail!("header: SH degree {} is not supported (0..3)", h.sh_degree);
        }
        // Sections may not share bytes: a file whose sections overlap was not written by us and
        // would decode one array from another's bytes.
        let mut spans: Vec<(u64, u64, &str)> = h
            .sections
            .iter()
            .filter(|s| s.bytes > 0)
            .map(|s| (s.offset, s.offset.saturating_add(s.bytes), s.name.as_str()))
            .collect();
        spans.sort();
        if let Some(w) = spans.windows(2).find(|w| w[1].0 < w[0].1) {
            bail!(
                "sections {:?} and {:?} overlap (bytes {}..{} and {}..{})",
                w[0].2,
                w[1].2,
                w[0].0,
                w[0].1,
                w[1].0,
                w[1].1
            );
        }
        let secs = Sections { list: h.sections.clone(), data };
        let packed = h.param_dtype == Dtype::Sog && h.version >= VERSION_PACKED;
        let param_sections = match h.param_dtype {
            Dtype::Sog if packed => 1,
            Dtype::Sog => 1 + h.groups.len(),
            _ => 5 * (1 + h.groups.len()),
        };
        let per_group = if h.offset_dtype == Dtype::Q8 { 2 } else { 3 };
        let known = param_sections + per_group * h.groups.len();
        if h.sections.len() != known {
            bail!("header lists {} sections; its groups need {known}", h.sections.len());
        }
        // Version 4's one bundle, cut into the background and each template by the header's counts.
        let mut parts: Vec<Scene> = Vec::new();
        if packed {
            let counts: Vec<usize> =
                std::iter::once(h.background_gaussians).chain(h.groups.iter().map(|g| g.template_gaussians)).collect();
            let total = counts
                .iter()
                .try_fold(0usize, |a, &b| a.checked_add(b))
                .ok_or_else(|| anyhow!("header: Gaussian counts overflow"))?;
            let all = secs.scene("gaussians", total, h.sh_degree, Dtype::Sog)?;
            let mut start = 0;
            for n in counts {
                parts.push(all.select(&(start..start + n).collect::<Vec<_>>()));
                start += n;
            }
        }
        let mut parts = parts.into_iter();
        let mut part = |name: &str, n: usize| match parts.next() {
            Some(s) => Ok(s),
            None => secs.scene(name, n, h.sh_degree, h.param_dtype),
        };
        let background = part("background", h.background_gaussians)?;
        let mut groups = Vec::new();
        for (i, g) in h.groups.iter().enumerate() {
            let template = part(&format!("group/{i}"), g.template_gaussians)?;
            let (k, t) = (g.instances.len(), g.template_gaussians);
            let v3 = |a: &[f32]| a.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect();
            let offsets = if h.offset_dtype == Dtype::Q8 {
                let steps = secs.get(&format!("group/{i}/d_steps"), &[3], Dtype::F32)?;
                let q = crate::formats::q8::OffsetCodes {
                    steps: [steps[0], steps[1], steps[2]],
                    codes: secs.blob(&format!("group/{i}/d_codes"), Dtype::Zstd)?.to_vec(),
                };
                let pairs = k.checked_mul(t).ok_or_else(|| anyhow!("group {:?}: too many pairs", g.name))?;
                q.decode(pairs, &format!("section \"group/{i}/d_codes\""))?
            } else if h.offset_dtype == Dtype::Pq8 {
                let n = crate::formats::pq8::CODES;
                let shapes = [vec![k, t, 2], vec![n, 3], vec![n, 4]];
                let mut arrays = Vec::new();
                for ((suffix, dtype), shape) in CODE_SECTIONS.into_iter().zip(shapes) {
                    arrays.push(secs.get(&format!("group/{i}/{suffix}"), &shape, dtype)?);
                }
                crate::formats::pq8::OffsetCodes {
                    codes: arrays[0].chunks_exact(2).map(|c| [c[0] as u8, c[1] as u8]).collect(),
                    dp: v3(&arrays[1]),
                    dc: arrays[2].chunks_exact(4).map(|c| [c[0], c[1], c[2], c[3]]).collect(),
                }
                .decode()
            } else {
                if ![Dtype::F32, Dtype::F16].contains(&h.offset_dtype) {
                    bail!("header: offset_dtype {:?} is not an offset storage (f32, f16, pq8, q8)", h.offset_dtype);
                }
                let mut off = Vec::new();
                for (suffix, width) in OFFSET_SECTIONS {
                    let shape = if width == 1 { vec![k, t] } else { vec![k, t, width] };
                    off.push(secs.get(&format!("group/{i}/{suffix}"), &shape, h.offset_dtype)?);
                }
                Offsets { d_means: v3(&off[0]), d_sh0: v3(&off[1]), d_opacities: std::mem::take(&mut off[2]) }
            };
            let instances = g
                .instances
                .iter()
                .map(|inst| {
                    let w = format!("group {:?} instance {:?}", g.name, inst.id);
                    Ok(Instance {
                        id: inst.id.clone(),
                        transform: Similarity::from_mat4(mat4_from_rows(&inst.transform), &w)?,
                    })
                })
                .collect::<Result<Vec<_>>>()?;
            groups.push(Group { name: g.name.clone(), template, instances, offsets });
        }
        let scene = InstancedScene { sh_degree: h.sh_degree, background, groups };
        scene.validate("contents")?;
        Ok(scene)
    };
    parse().with_context(|| what.to_string())
}

/// Reads an `.instgs` file.
pub fn read(path: &Path) -> Result<InstancedScene> {
    Ok(read_with_storage(path)?.0)
}

/// Reads an `.instgs` file and how it is stored (the player's editor saves the same way).
pub fn read_with_storage(path: &Path) -> Result<(InstancedScene, Storage)> {
    let what = path.display().to_string();
    let bytes = std::fs::read(path).with_context(|| format!("{what}: cannot read"))?;
    let scene = from_bytes(&bytes, &what)?;
    let (header, _, _) = split(&bytes).with_context(|| what.clone())?;
    Ok((scene, Storage { offsets: header.offset_dtype, params: header.param_dtype }))
}

/// Bytes of every part of a file: header (with padding), background, each group's template and
/// offsets (version 4's one bundle: "background and templates", the templates at 0 bytes).
pub fn part_bytes(bytes: &[u8]) -> Result<Vec<PartBytes>> {
    let (h, _, start) = split(bytes)?;
    let mut parts = vec![PartBytes { name: "header".into(), bytes: start }];
    let sum = |prefix: &str, offsets: bool| -> u64 {
        h.sections
            .iter()
            .filter(|s| {
                s.name.strip_prefix(prefix).is_some_and(|r| r.starts_with('/') && r[1..].starts_with("d_") == offsets)
            })
            .map(|s| s.bytes.div_ceil(16) * 16)
            .sum()
    };
    if h.sections.iter().any(|s| s.name == PACKED_SECTION) {
        parts.push(PartBytes { name: "background and templates".into(), bytes: sum("gaussians", false) });
    } else {
        parts.push(PartBytes { name: "background".into(), bytes: sum("background", false) });
    }
    for (i, g) in h.groups.iter().enumerate() {
        parts.push(PartBytes { name: format!("{}/template", g.name), bytes: sum(&format!("group/{i}"), false) });
        parts.push(PartBytes { name: format!("{}/offsets", g.name), bytes: sum(&format!("group/{i}"), true) });
    }
    Ok(parts)
}
