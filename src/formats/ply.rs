//! The Inria 3DGS PLY (binary little-endian; ASCII and big-endian are read too):
//! `x y z [nx ny nz] f_dc_0..2 f_rest_* opacity scale_0..2 rot_0..3`, SH degree 0–3 inferred
//! from the number of `f_rest_*` (0, 9, 24 or 45), `f_rest` channel-major as Inria writes it,
//! opacity as a logit, scales as natural logs, rotation as a (w, x, y, z) quaternion. Unknown
//! extra properties and elements are ignored. Also SuperSplat's `.compressed.ply` (chunks of
//! 256 splats with quantisation bounds, packed 32-bit fields, optional 8-bit SH), read and
//! written.
use std::io::{BufRead, BufReader, BufWriter, Read, Write};
use std::path::Path;

use anyhow::{anyhow, bail, Context, Result};
use ply_rs_bw::parser::Parser;
use ply_rs_bw::ply::{ElementDef, Encoding, PropertyAccess, PropertyAccessResult, PropertyType, ScalarType};

use crate::formats::quant::{largest_component, OPACITY_LOGIT_LIMIT};
use crate::math::SH_C0_F32;
use crate::model::scene::Scene;

/// Number of values a plain-PLY row can carry: 14 core + 45 f_rest.
const ROW: usize = 59;

/// One vertex row of a plain 3DGS PLY: x y z, f_dc 0..2, opacity, scale 0..2, rot 0..3 at
/// slots 0..14, then f_rest_j at 14 + j.
struct GaussRow([f32; ROW]);

fn core_slot(name: &str) -> Option<usize> {
    Some(match name {
        "x" => 0,
        "y" => 1,
        "z" => 2,
        "f_dc_0" => 3,
        "f_dc_1" => 4,
        "f_dc_2" => 5,
        "opacity" => 6,
        "scale_0" => 7,
        "scale_1" => 8,
        "scale_2" => 9,
        "rot_0" => 10,
        "rot_1" => 11,
        "rot_2" => 12,
        "rot_3" => 13,
        _ => {
            let j: usize = name.strip_prefix("f_rest_")?.parse().ok()?;
            return (j < 45).then_some(14 + j);
        }
    })
}

const CORE: [&str; 14] = [
    "x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2",
    "rot_3",
];

impl GaussRow {
    fn put(&mut self, name: &str, v: f32) -> PropertyAccessResult {
        match core_slot(name) {
            Some(s) => {
                self.0[s] = v;
                PropertyAccessResult::Set
            }
            None => PropertyAccessResult::Ignored,
        }
    }
}

impl PropertyAccess for GaussRow {
    fn new() -> Self {
        GaussRow([0.0; ROW])
    }
    fn set_float(&mut self, n: &str, v: f32) -> PropertyAccessResult {
        self.put(n, v)
    }
    fn set_double(&mut self, n: &str, v: f64) -> PropertyAccessResult {
        self.put(n, v as f32)
    }
    fn set_char(&mut self, n: &str, v: i8) -> PropertyAccessResult {
        self.put(n, v as f32)
    }
    fn set_uchar(&mut self, n: &str, v: u8) -> PropertyAccessResult {
        self.put(n, v as f32)
    }
    fn set_short(&mut self, n: &str, v: i16) -> PropertyAccessResult {
        self.put(n, v as f32)
    }
    fn set_ushort(&mut self, n: &str, v: u16) -> PropertyAccessResult {
        self.put(n, v as f32)
    }
    fn set_int(&mut self, n: &str, v: i32) -> PropertyAccessResult {
        self.put(n, v as f32)
    }
    fn set_uint(&mut self, n: &str, v: u32) -> PropertyAccessResult {
        self.put(n, v as f32)
    }
}

/// A chunk row of a compressed PLY: min/max of position, log-scale and colour.
struct ChunkRow([f32; 18]);

const CHUNK_PROPS: [&str; 18] = [
    "min_x",
    "min_y",
    "min_z",
    "max_x",
    "max_y",
    "max_z",
    "min_scale_x",
    "min_scale_y",
    "min_scale_z",
    "max_scale_x",
    "max_scale_y",
    "max_scale_z",
    "min_r",
    "min_g",
    "min_b",
    "max_r",
    "max_g",
    "max_b",
];

impl PropertyAccess for ChunkRow {
    fn new() -> Self {
        // Colour bounds default to [0, 1] (files without them store plain 8-bit colour).
        let mut v = [0.0; 18];
        v[15..18].fill(1.0);
        ChunkRow(v)
    }
    fn set_float(&mut self, n: &str, v: f32) -> PropertyAccessResult {
        match CHUNK_PROPS.iter().position(|p| *p == n) {
            Some(s) => {
                self.0[s] = v;
                PropertyAccessResult::Set
            }
            None => PropertyAccessResult::Ignored,
        }
    }
}

/// A vertex row of a compressed PLY.
struct PackedRow([u32; 4]);

const PACKED_PROPS: [&str; 4] = ["packed_position", "packed_rotation", "packed_scale", "packed_color"];

impl PropertyAccess for PackedRow {
    fn new() -> Self {
        PackedRow([0; 4])
    }
    fn set_uint(&mut self, n: &str, v: u32) -> PropertyAccessResult {
        match PACKED_PROPS.iter().position(|p| *p == n) {
            Some(s) => {
                self.0[s] = v;
                PropertyAccessResult::Set
            }
            None => PropertyAccessResult::Ignored,
        }
    }
}

/// Any element we skip.
struct Ignore;

impl PropertyAccess for Ignore {
    fn new() -> Self {
        Ignore
    }
}

fn prop_names(e: &ElementDef) -> Vec<&str> {
    e.properties.keys().map(|k| k.as_str()).collect()
}

/// Reads a plain 3DGS PLY or a SuperSplat compressed PLY and validates it.
pub fn read_ply(path: &Path) -> Result<Scene> {
    let what = path.display().to_string();
    let file = std::fs::File::open(path).with_context(|| format!("{what}: cannot open"))?;
    from_reader(BufReader::new(file), &what)
}

/// [`read_ply`] on bytes in memory; `what` names them in errors.
pub fn from_bytes(bytes: &[u8], what: &str) -> Result<Scene> {
    from_reader(bytes, what)
}

/// The longest PLY header read (a 3DGS header with 45 `f_rest` is about 1.5 KB).
const MAX_HEADER_BYTES: usize = 1 << 20;

/// Reads the PLY header up to `end_header` and refuses an element declared twice, or a property
/// declared twice in one element (the parser would keep one silently and then misread the
/// data). Returns a reader that yields the header again, then the data.
pub fn checked_reader<R: BufRead>(mut r: R, what: &str) -> Result<impl BufRead> {
    let mut header = Vec::new();
    let mut elements: Vec<String> = Vec::new();
    let mut properties: Vec<String> = Vec::new();
    loop {
        let start = header.len();
        let n = r
            .by_ref()
            .take((MAX_HEADER_BYTES - start) as u64)
            .read_until(b'\n', &mut header)
            .with_context(|| format!("{what}: cannot read"))?;
        if n == 0 {
            break; // the parser names what is missing
        }
        if header.len() >= MAX_HEADER_BYTES {
            bail!("{what}: no end_header in the first {MAX_HEADER_BYTES} bytes (not a PLY?)");
        }
        let line = String::from_utf8_lossy(&header[start..]);
        let words: Vec<&str> = line.split_whitespace().collect();
        match words.as_slice() {
            ["end_header"] => break,
            ["element", name, ..] => {
                if elements.iter().any(|e| e == name) {
                    bail!("{what}: element '{name}' is declared twice in the header");
                }
                elements.push(name.to_string());
                properties.clear();
            }
            ["property", .., name] if words.len() >= 3 => {
                if properties.iter().any(|p| p == name) {
                    let element = elements.last().map(String::as_str).unwrap_or("?");
                    bail!("{what}: property '{name}' of element '{element}' is declared twice in the header");
                }
                properties.push(name.to_string());
            }
            _ => {}
        }
    }
    Ok(std::io::Cursor::new(header).chain(r))
}

/// The declared type of a property as the header spells it.
fn type_name(t: &PropertyType) -> String {
    fn scalar(s: &ScalarType) -> &'static str {
        match s {
            ScalarType::Char => "char",
            ScalarType::UChar => "uchar",
            ScalarType::Short => "short",
            ScalarType::UShort => "ushort",
            ScalarType::Int => "int",
            ScalarType::UInt => "uint",
            ScalarType::Float => "float",
            ScalarType::Double => "double",
        }
    }
    match t {
        PropertyType::Scalar(s) => scalar(s).to_string(),
        PropertyType::List(i, s) => format!("list {} {}", scalar(i), scalar(s)),
    }
}

/// Refuses a property of `element` whose declared type is not one of `allowed` (it would be
/// read as 0 without a word).
fn expect_type(what: &str, element: &ElementDef, name: &str, allowed: &[ScalarType]) -> Result<()> {
    if let Some(p) = element.properties.get(name) {
        let ok = matches!(&p.data_type, PropertyType::Scalar(s) if allowed.contains(s));
        if !ok {
            let want: Vec<String> = allowed.iter().map(|s| type_name(&PropertyType::Scalar(s.clone()))).collect();
            bail!(
                "{what}: {} property '{name}' is declared {}; expected {}",
                element.name,
                type_name(&p.data_type),
                want.join(" or ")
            );
        }
    }
    Ok(())
}

const FLOATS: [ScalarType; 2] = [ScalarType::Float, ScalarType::Double];

fn from_reader<R: BufRead>(reader: R, what: &str) -> Result<Scene> {
    let mut reader = ply_rs_bw::parser::Reader::new(checked_reader(reader, what)?);
    let header = Parser::<Ignore>::new()
        .read_header(&mut reader)
        .map_err(|e| anyhow!("{what}: not a valid PLY header: {}", first_line(&e.to_string())))?;
    let vertex = header.elements.get("vertex").ok_or_else(|| anyhow!("{what}: the PLY has no 'vertex' element"))?;
    let compressed = header.elements.contains_key("chunk") && vertex.properties.contains_key("packed_position");
    let scene = if compressed {
        read_compressed(what, &mut reader, &header)?
    } else {
        let names = prop_names(vertex);
        for p in CORE {
            if !names.contains(&p) {
                bail!("{what}: vertex property '{p}' is missing (not a 3DGS PLY?)");
            }
        }
        let rest = names.iter().filter(|n| n.starts_with("f_rest_")).count();
        let sh_degree = match rest {
            0 => 0,
            9 => 1,
            24 => 2,
            45 => 3,
            k => bail!("{what}: {k} f_rest properties; expected 0, 9, 24 or 45 (SH degree 0-3)"),
        };
        for j in 0..rest {
            if !names.contains(&format!("f_rest_{j}").as_str()) {
                bail!("{what}: vertex property 'f_rest_{j}' is missing");
            }
        }
        for name in &names {
            if core_slot(name).is_some() {
                expect_type(what, vertex, name, &FLOATS)?;
            }
        }
        let mut rows = Vec::new();
        for (name, def) in &header.elements {
            if name == "vertex" {
                rows = Parser::<GaussRow>::new()
                    .read_payload_for_element(&mut reader, def, &header)
                    .map_err(|e| anyhow!("{what}: truncated or corrupt vertex data: {}", first_line(&e.to_string())))?;
            } else {
                Parser::<Ignore>::new().read_payload_for_element(&mut reader, def, &header).map_err(|e| {
                    anyhow!("{what}: truncated or corrupt '{name}' data: {}", first_line(&e.to_string()))
                })?;
            }
        }
        scene_from_rows(&rows, sh_degree)
    };
    if header.encoding != Encoding::Ascii {
        // Binary files must end where the header says.
        let mut extra = [0u8; 1];
        let inner = reader.get_mut();
        if inner.read(&mut extra).unwrap_or(0) != 0 {
            bail!("{what}: data continues past the elements the header declares");
        }
    }
    scene.validate(what)?;
    Ok(scene)
}

fn first_line(s: &str) -> &str {
    s.lines().next().unwrap_or(s)
}

fn scene_from_rows(rows: &[GaussRow], sh_degree: u32) -> Scene {
    let coeffs = ((sh_degree + 1) * (sh_degree + 1)) as usize;
    let rest = coeffs - 1;
    let mut s = Scene { sh_degree, ..Default::default() };
    s.means.reserve(rows.len());
    s.sh.reserve(rows.len() * coeffs * 3);
    for r in rows {
        let v = &r.0;
        s.means.push([v[0], v[1], v[2]]);
        // ±inf (other tools' fully opaque or transparent splats) clamps like our decoders;
        // NaN passes through to `validate`, which refuses it.
        s.opacities.push(if v[6].is_infinite() { v[6].signum() * OPACITY_LOGIT_LIMIT } else { v[6] });
        s.scales.push([v[7], v[8], v[9]]);
        s.quats.push([v[10], v[11], v[12], v[13]]);
        s.sh.extend_from_slice(&v[3..6]);
        for k in 0..rest {
            for c in 0..3 {
                s.sh.push(v[14 + c * rest + k]);
            }
        }
    }
    s
}

fn read_compressed<R: std::io::BufRead>(
    what: &str,
    reader: &mut ply_rs_bw::parser::Reader<R>,
    header: &ply_rs_bw::ply::Header,
) -> Result<Scene> {
    let mut chunks = Vec::new();
    let mut packed = Vec::new();
    let mut sh_rows: Vec<ShRow> = Vec::new();
    let mut sh_degree = 0;
    for (name, def) in &header.elements {
        let err = |e: ply_rs_bw::parser::ParseError| {
            anyhow!("{what}: truncated or corrupt '{name}' data: {}", first_line(&e.to_string()))
        };
        match name.as_str() {
            "chunk" => {
                for p in &CHUNK_PROPS[..12] {
                    if !def.properties.contains_key(*p) {
                        bail!("{what}: chunk property '{p}' is missing");
                    }
                }
                for p in CHUNK_PROPS {
                    expect_type(what, def, p, &[ScalarType::Float])?;
                }
                chunks = Parser::<ChunkRow>::new().read_payload_for_element(reader, def, header).map_err(err)?;
            }
            "vertex" => {
                for p in PACKED_PROPS {
                    if !def.properties.contains_key(p) {
                        bail!("{what}: vertex property '{p}' is missing");
                    }
                    expect_type(what, def, p, &[ScalarType::UInt])?;
                }
                packed = Parser::<PackedRow>::new().read_payload_for_element(reader, def, header).map_err(err)?;
            }
            "sh" => {
                let rest = def.properties.keys().filter(|k| k.starts_with("f_rest_")).count();
                sh_degree = match rest {
                    9 => 1,
                    24 => 2,
                    45 => 3,
                    k => bail!("{what}: the 'sh' element has {k} f_rest properties; expected 9, 24 or 45"),
                };
                for j in 0..rest {
                    match def.properties.get(&format!("f_rest_{j}")).map(|p| &p.data_type) {
                        Some(ply_rs_bw::ply::PropertyType::Scalar(ply_rs_bw::ply::ScalarType::UChar)) => {}
                        Some(_) => bail!("{what}: 'sh' property 'f_rest_{j}' must be a uchar"),
                        None => bail!("{what}: 'sh' property 'f_rest_{j}' is missing"),
                    }
                }
                sh_rows = Parser::<ShRow>::new().read_payload_for_element(reader, def, header).map_err(err)?;
            }
            _ => {
                Parser::<Ignore>::new().read_payload_for_element(reader, def, header).map_err(err)?;
            }
        }
    }
    if chunks.len() * 256 < packed.len() {
        bail!("{what}: {} chunks cannot hold {} splats (256 per chunk)", chunks.len(), packed.len());
    }
    if sh_degree > 0 && sh_rows.len() != packed.len() {
        bail!("{what}: {} 'sh' rows for {} splats", sh_rows.len(), packed.len());
    }
    let mut scene = decode_compressed(&chunks, &packed);
    if sh_degree > 0 {
        add_compressed_sh(&mut scene, &sh_rows, sh_degree);
    }
    Ok(scene)
}

/// A row of a compressed PLY's `sh` element: `f_rest_*` bytes, channel-major.
struct ShRow(Vec<u8>);

impl PropertyAccess for ShRow {
    fn new() -> Self {
        ShRow(vec![0; 45])
    }
    fn set_uchar(&mut self, n: &str, v: u8) -> PropertyAccessResult {
        match n.strip_prefix("f_rest_").and_then(|k| k.parse::<usize>().ok()).filter(|&k| k < 45) {
            Some(k) => {
                self.0[k] = v;
                PropertyAccessResult::Set
            }
            None => PropertyAccessResult::Ignored,
        }
    }
}

/// SuperSplat's SH byte: 0 and 255 are the ends of ±4, the rest bin centres.
fn sh_from_byte(b: u8) -> f32 {
    let t = match b {
        0 => 0.0,
        255 => 1.0,
        _ => (b as f32 + 0.5) / 256.0,
    };
    (t - 0.5) * 8.0
}

/// The inverse of `sh_from_byte` (SuperSplat's writer: truncating (v / 8 + 0.5)·256).
pub fn sh_to_byte(v: f32) -> u8 {
    ((v / 8.0 + 0.5) * 256.0).clamp(0.0, 255.0) as u8
}

fn add_compressed_sh(scene: &mut Scene, rows: &[ShRow], degree: u32) {
    let coeffs = ((degree + 1) * (degree + 1)) as usize;
    let rest = coeffs - 1;
    let mut sh = Vec::with_capacity(scene.len() * coeffs * 3);
    for (i, row) in rows.iter().enumerate() {
        sh.extend_from_slice(&scene.sh[i * 3..i * 3 + 3]);
        for k in 0..rest {
            for c in 0..3 {
                sh.push(sh_from_byte(row.0[c * rest + k]));
            }
        }
    }
    scene.sh = sh;
    scene.sh_degree = degree;
}

fn unorm(v: u32, bits: u32) -> f32 {
    let m = (1u32 << bits) - 1;
    (v & m) as f32 / m as f32
}

fn unpack_111011(v: u32) -> [f32; 3] {
    [unorm(v >> 21, 11), unorm(v >> 11, 10), unorm(v, 11)]
}

fn lerp(a: f32, b: f32, t: f32) -> f32 {
    a * (1.0 - t) + b * t
}

fn decode_compressed(chunks: &[ChunkRow], packed: &[PackedRow]) -> Scene {
    let mut s = Scene::default();
    for (i, p) in packed.iter().enumerate() {
        let c = &chunks[i / 256].0;
        let [pos, rot, scl, col] = p.0;
        let t = unpack_111011(pos);
        s.means.push([lerp(c[0], c[3], t[0]), lerp(c[1], c[4], t[1]), lerp(c[2], c[5], t[2])]);
        let t = unpack_111011(scl);
        s.scales.push([lerp(c[6], c[9], t[0]), lerp(c[7], c[10], t[1]), lerp(c[8], c[11], t[2])]);
        // Rotation: top 2 bits index the largest component, dropped; the other three follow
        // in (w, x, y, z) order, 10 bits each, in [-1/sqrt2, 1/sqrt2].
        let norm = std::f32::consts::SQRT_2;
        let abc = [20u32, 10, 0].map(|sh| (unorm(rot >> sh, 10) - 0.5) * norm);
        let m = (1.0 - abc.iter().map(|v| v * v).sum::<f32>()).max(0.0).sqrt();
        let largest = (rot >> 30) as usize;
        let mut q = [0.0f32; 4];
        let mut k = 0;
        for (j, qj) in q.iter_mut().enumerate() {
            if j == largest {
                *qj = m;
            } else {
                *qj = abc[k];
                k += 1;
            }
        }
        s.quats.push(q);
        let rgba = [24u32, 16, 8, 0].map(|sh| unorm(col >> sh, 8));
        for ch in 0..3 {
            let v = lerp(c[12 + ch], c[15 + ch], rgba[ch]);
            s.sh.push((v - 0.5) / SH_C0_F32);
        }
        // Opacity 0 or 1 has an infinite logit; clamp to the middle of the outer 8-bit bins'
        // outer halves (ln 1019), as the shared decoded PLYs do.
        let a = rgba[3].clamp(1.0 / 1020.0, 1019.0 / 1020.0);
        s.opacities.push((a / (1.0 - a)).ln());
    }
    s
}

/// Writes `scene` as a binary little-endian Inria 3DGS PLY (zero normals, `f_rest`
/// channel-major), through a temporary file renamed into place; a scene [`read_ply`] would
/// refuse (`Scene::validate`) is not written.
pub fn write_ply(scene: &Scene, path: &Path) -> Result<()> {
    scene.validate(&format!("{}: not written", path.display()))?;
    let coeffs = scene.sh_coeffs();
    let rest = coeffs - 1;
    let mut header = format!("ply\nformat binary_little_endian 1.0\nelement vertex {}\n", scene.len());
    for p in ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] {
        header += &format!("property float {p}\n");
    }
    for j in 0..3 * rest {
        header += &format!("property float f_rest_{j}\n");
    }
    for p in ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"] {
        header += &format!("property float {p}\n");
    }
    header += "end_header\n";
    crate::util::write_atomic(path, |w| {
        let mut w = BufWriter::new(w);
        w.write_all(header.as_bytes())?;
        let mut row: Vec<f32> = Vec::with_capacity(17 + 3 * rest);
        for i in 0..scene.len() {
            row.clear();
            row.extend_from_slice(&scene.means[i]);
            row.extend_from_slice(&[0.0; 3]);
            let sh = &scene.sh[i * coeffs * 3..(i + 1) * coeffs * 3];
            row.extend_from_slice(&sh[..3]);
            for c in 0..3 {
                for k in 1..coeffs {
                    row.push(sh[k * 3 + c]);
                }
            }
            row.push(scene.opacities[i]);
            row.extend_from_slice(&scene.scales[i]);
            row.extend_from_slice(&scene.quats[i]);
            for v in &row {
                w.write_all(&v.to_le_bytes())?;
            }
        }
        w.flush()?;
        Ok(())
    })
}

fn pack_unorm(v: f32, bits: u32) -> u32 {
    let m = ((1u32 << bits) - 1) as f32;
    (v * m + 0.5).floor().clamp(0.0, m) as u32
}

/// Writes `scene` as a SuperSplat compressed PLY: chunks of 256 splats in file order with
/// their position, log-scale (clamped to ±20) and colour bounds; per splat position and scale
/// 11/10/11 bits within the bounds, rotation as the largest component's index and the other
/// three in 10 bits, colour and opacity 8 bits; SH bands (if any) as an `sh` element of bytes,
/// channel-major as Inria's `f_rest` (SuperSplat's ±4 range).
pub fn write_compressed_ply(scene: &Scene, path: &Path) -> Result<()> {
    scene.validate(&format!("{}: not written", path.display()))?;
    let n = scene.len();
    let coeffs = scene.sh_coeffs();
    let rest = coeffs - 1;
    let chunks = n.div_ceil(256);
    let mut header = String::from("ply\nformat binary_little_endian 1.0\ncomment written by instgs-vk\n");
    header += &format!("element chunk {chunks}\n");
    for p in CHUNK_PROPS {
        header += &format!("property float {p}\n");
    }
    header += &format!("element vertex {n}\n");
    for p in PACKED_PROPS {
        header += &format!("property uint {p}\n");
    }
    if rest > 0 {
        header += &format!("element sh {n}\n");
        for j in 0..3 * rest {
            header += &format!("property uchar f_rest_{j}\n");
        }
    }
    header += "end_header\n";
    let colour = |i: usize, c: usize| 0.5 + SH_C0_F32 * scene.sh[i * coeffs * 3 + c];
    let mut chunk_rows = Vec::with_capacity(chunks * 18);
    let mut packed = Vec::with_capacity(n * 4);
    for c in 0..chunks {
        let range = c * 256..((c + 1) * 256).min(n);
        let bounds = |f: &dyn Fn(usize) -> [f32; 3]| {
            let mut lo = [f32::MAX; 3];
            let mut hi = [f32::MIN; 3];
            for i in range.clone() {
                let v = f(i);
                for a in 0..3 {
                    lo[a] = lo[a].min(v[a]);
                    hi[a] = hi[a].max(v[a]);
                }
            }
            (lo, hi)
        };
        let (plo, phi) = bounds(&|i| scene.means[i]);
        let (slo, shi) = bounds(&|i| scene.scales[i].map(|v| v.clamp(-20.0, 20.0)));
        let (clo, chi) = bounds(&|i| [colour(i, 0), colour(i, 1), colour(i, 2)]);
        for v in [plo, phi, slo, shi, clo, chi] {
            chunk_rows.extend_from_slice(&v);
        }
        let norm = |v: f32, lo: f32, hi: f32| if hi - lo < 1e-5 { 0.0 } else { ((v - lo) / (hi - lo)).clamp(0.0, 1.0) };
        let pack3 = |v: [f32; 3], lo: [f32; 3], hi: [f32; 3]| {
            pack_unorm(norm(v[0], lo[0], hi[0]), 11) << 21
                | pack_unorm(norm(v[1], lo[1], hi[1]), 10) << 11
                | pack_unorm(norm(v[2], lo[2], hi[2]), 11)
        };
        for i in range {
            let position = pack3(scene.means[i], plo, phi);
            let scale = pack3(scene.scales[i].map(|v| v.clamp(-20.0, 20.0)), slo, shi);
            let (largest, q) = largest_component(scene.quats[i]);
            let mut rotation = largest as u32;
            for (j, v) in q.iter().enumerate() {
                if j != largest {
                    rotation = rotation << 10 | pack_unorm(v * std::f32::consts::FRAC_1_SQRT_2 + 0.5, 10);
                }
            }
            let rgb: [u32; 3] = std::array::from_fn(|ch| pack_unorm(norm(colour(i, ch), clo[ch], chi[ch]), 8));
            let alpha = pack_unorm(1.0 / (1.0 + (-scene.opacities[i]).exp()), 8);
            let colour = rgb[0] << 24 | rgb[1] << 16 | rgb[2] << 8 | alpha;
            packed.extend_from_slice(&[position, rotation, scale, colour]);
        }
    }
    crate::util::write_atomic(path, |w| {
        let mut w = BufWriter::new(w);
        w.write_all(header.as_bytes())?;
        for v in &chunk_rows {
            w.write_all(&v.to_le_bytes())?;
        }
        for v in &packed {
            w.write_all(&v.to_le_bytes())?;
        }
        for i in 0..n {
            let sh = &scene.sh[i * coeffs * 3..(i + 1) * coeffs * 3];
            for c in 0..3 {
                for k in 1..coeffs {
                    w.write_all(&[sh_to_byte(sh[k * 3 + c])])?;
                }
            }
        }
        w.flush()?;
        Ok(())
    })
}
