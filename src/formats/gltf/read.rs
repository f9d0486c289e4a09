//! Reading glTF: splat primitives placed by their nodes, or the instanced scene our extras
//! describe.
use std::cell::RefCell;
use std::collections::{HashMap, HashSet};
use std::path::Path;
use std::rc::Rc;

use anyhow::{anyhow, bail, Context, Result};
use glam::Mat4;
use gltf::accessor::DataType;
use gltf::mesh::Semantic;
use serde_json::{json, Value};

use super::{half_turn_z, sh_name, GltfScene, EXTENSION, KNOWN_REQUIRED, PREFIX, TEMPLATE_ATTRIBUTES};
use crate::formats::quant::OPACITY_LOGIT_LIMIT;
use crate::model::instanced::{Group, Instance, InstancedScene, Offsets, Similarity};
use crate::model::scene::Scene;

/// Whether `bytes` (a file's start or whole) look like glTF: the GLB magic, or JSON with an
/// `asset` object (a `.gltf`).
pub fn looks_like_gltf(head: &[u8], path: &Path) -> bool {
    if head.starts_with(b"glTF") {
        return true;
    }
    let ext = path.extension().map(|e| e.to_string_lossy().to_ascii_lowercase()).unwrap_or_default();
    ext == "gltf"
        || std::fs::read(path)
            .ok()
            .and_then(|b| serde_json::from_slice::<Value>(&b).ok())
            .is_some_and(|v| v.get("asset").is_some_and(|a| a.get("version").is_some()))
}

/// Reads a `.glb`/`.gltf` file: an instanced scene when it carries our extras, else plain.
pub fn read(path: &Path) -> Result<GltfScene> {
    let what = path.display().to_string();
    let bytes = std::fs::read(path).with_context(|| format!("{what}: cannot read"))?;
    from_bytes(&bytes, &what, Some(path))
}

/// Reads glTF from memory; `file`, the file it came from, resolves a `.gltf`'s relative buffer
/// URIs inside its folder (`crate::limits::confined`; None: only the BIN chunk and `data:` URIs
/// are read).
pub fn from_bytes(bytes: &[u8], what: &str, file: Option<&Path>) -> Result<GltfScene> {
    let (json, blob) = if bytes.starts_with(b"glTF") {
        let glb = gltf::binary::Glb::from_slice(bytes).map_err(|e| anyhow!("{what}: not a valid GLB: {e}"))?;
        (glb.json.into_owned(), glb.bin.map(|b| b.into_owned()))
    } else {
        (bytes.to_vec(), None)
    };
    let mut doc: Value =
        serde_json::from_slice(&json).map_err(|e| anyhow!("{what}: the glTF JSON does not parse: {e}"))?;
    // gltf-json keeps attribute names it does not know only when they start with '_': the
    // extension's get one. Application-specific attributes (already '_'-prefixed) other than
    // our templates' rows are dropped first, so that none — `_KHR_gaussian_splatting:SCALE`,
    // say — can stand in for the extension's: attribute names are matched exactly.
    for mesh in doc.get_mut("meshes").and_then(|m| m.as_array_mut()).into_iter().flatten() {
        for prim in mesh.get_mut("primitives").and_then(|p| p.as_array_mut()).into_iter().flatten() {
            if let Some(Value::Object(attrs)) = prim.get_mut("attributes") {
                *attrs = std::mem::take(attrs)
                    .into_iter()
                    .filter(|(k, _)| !k.starts_with('_') || TEMPLATE_ATTRIBUTES.contains(&k.as_str()))
                    .map(|(k, v)| if k.starts_with(PREFIX) { (format!("_{k}"), v) } else { (k, v) })
                    .collect();
            }
        }
    }
    // Accessors without a buffer view (glTF: zeros, or data an extension provides, as
    // KHR_gaussian_splatting_compression_spz_2's do) are refused by gltf-json's validation:
    // each is pointed at one extra view of buffer 0 here and remembered, so that they are
    // never read as data (`Ctx::values`).
    let dataless: HashSet<usize> = doc
        .get("accessors")
        .and_then(Value::as_array)
        .into_iter()
        .flatten()
        .enumerate()
        .filter(|(_, a)| a.is_object() && a.get("bufferView").is_none() && a.get("sparse").is_none())
        .map(|(i, _)| i)
        .collect();
    if !dataless.is_empty() {
        if doc.get("buffers").and_then(Value::as_array).is_none_or(Vec::is_empty) {
            bail!("{what}: accessors without a buffer view in a file without buffers");
        }
        let extra = json!({"buffer": 0, "byteLength": 1});
        let views = match doc.get_mut("bufferViews").and_then(Value::as_array_mut) {
            Some(v) => {
                v.push(extra);
                v.len() - 1
            }
            None => {
                doc["bufferViews"] = json!([extra]);
                0
            }
        };
        for &i in &dataless {
            doc["accessors"][i]["bufferView"] = json!(views);
        }
    }
    let mut root: gltf::json::Root =
        serde_json::from_value(doc).map_err(|e| anyhow!("{what}: not a glTF 2.0 document: {e}"))?;
    if let Some(ext) = root.extensions_required.iter().find(|e| !KNOWN_REQUIRED.contains(&e.as_str())) {
        bail!(
            "{what}: the file requires the glTF extension {ext}, which we do not read (we read {})",
            KNOWN_REQUIRED.join(", ")
        );
    }
    // Checked here; gltf-json knows neither and would refuse them.
    root.extensions_required.clear();
    // gltf-json's validation indexes the accessors by POSITION unchecked: check first.
    let accessors = root.accessors.len();
    for (m, mesh) in root.meshes.iter().enumerate() {
        for prim in &mesh.primitives {
            if let Some(i) = prim.attributes.values().map(|i| i.value()).find(|&i| i >= accessors) {
                bail!("{what}: mesh {m} names accessor {i}; the file has {accessors}");
            }
        }
    }
    let document = gltf::Document::from_json(root).map_err(|e| anyhow!("{what}: an invalid glTF document: {e}"))?;
    let buffers = super::buffers::load_buffers(&document, what, file, blob)?;
    let ctx = Ctx { what, buffers, dataless, cache: RefCell::new(HashMap::new()) };
    let splats = splat_primitives(&document, what)?;
    if splats.is_empty() {
        bail!("{what}: a glTF file without {EXTENSION} primitives (no splats in its scene)");
    }
    // The node graph expanded: every visit of a splat primitive is its splats again (a graph
    // that reuses its children multiplies them), checked before any is decoded.
    let count = |p: &SplatPrimitive| -> u64 {
        let prim = document.nodes().nth(p.node).and_then(|n| n.mesh()).and_then(|m| m.primitives().nth(p.primitive));
        prim.map_or(0, |q| match q.indices() {
            Some(i) => i.count() as u64,
            None => q.get(&Semantic::Positions).map_or(0, |a| a.count() as u64),
        })
    };
    let total: u64 = splats.iter().map(count).sum();
    crate::limits::check_bytes(
        what,
        &format!("its {} splat primitive visits ({total} splats)", splats.len()),
        total.saturating_mul(BYTES_PER_SPLAT),
    )?;
    let extras = document.as_json().extras.as_ref().and_then(|e| serde_json::from_str::<Value>(e.get()).ok());
    if let Some(x) = extras.as_ref().and_then(|e| e.get("instgs")) {
        match super::instanced::read_instanced(&ctx, &document, &splats, x) {
            Ok(scene) => return Ok(GltfScene::Instanced(scene)),
            Err(e) => {
                eprintln!("note: {what}: its instgs extras do not describe its nodes ({e:#}); read as a plain scene")
            }
        }
    }
    let mut scene = Scene::default();
    for p in &splats {
        let s = ctx.placed(p, &document)?;
        scene = append_any_degree(scene, s);
    }
    half_turn_z(&mut scene);
    scene.validate(what)?;
    Ok(GltfScene::Plain(scene))
}

/// Host bytes of one splat as we hold it (degree 3: mean, scales, quaternion, opacity, 48 SH
/// values, f32 each), for the memory budget.
pub(super) const BYTES_PER_SPLAT: u64 = 4 * (3 + 3 + 4 + 1 + 48);

/// One splat primitive of the scene: node, primitive index, world matrix.
pub(super) struct SplatPrimitive {
    pub(super) node: usize,
    pub(super) primitive: usize,
    pub(super) world: Mat4,
}

/// Every splat primitive of the default scene (scene 0 when none is named) with its node's
/// world matrix; the node graph walked depth-first (at most 64 deep, 2²⁰ visits).
fn splat_primitives(doc: &gltf::Document, what: &str) -> Result<Vec<SplatPrimitive>> {
    let scene = doc
        .default_scene()
        .or_else(|| doc.scenes().next())
        .ok_or_else(|| anyhow!("{what}: a glTF file with no scene"))?;
    let mut out = Vec::new();
    let mut stack: Vec<(gltf::Node, Mat4, usize)> = scene.nodes().map(|n| (n, Mat4::IDENTITY, 0)).collect();
    let mut visits = 0usize;
    while let Some((node, parent, depth)) = stack.pop() {
        visits += 1;
        if depth > 64 || visits > 1 << 20 {
            bail!("{what}: the node graph is deeper than 64 or has more than 2^20 node visits (a cycle?)");
        }
        let world = parent * Mat4::from_cols_array_2d(&node.transform().matrix());
        if let Some(mesh) = node.mesh() {
            for prim in mesh.primitives() {
                if prim.extensions().is_some_and(|e| e.contains_key(EXTENSION)) {
                    out.push(SplatPrimitive { node: node.index(), primitive: prim.index(), world });
                }
            }
        }
        stack.extend(node.children().map(|c| (c, world, depth + 1)));
    }
    out.sort_by_key(|p| (p.node, p.primitive));
    Ok(out)
}

/// `a` with `b` appended, the lower SH degree padded with zero coefficients.
pub(super) fn append_any_degree(a: Scene, b: Scene) -> Scene {
    if a.is_empty() {
        return b;
    }
    let degree = a.sh_degree.max(b.sh_degree);
    let (mut a, b) = (a.with_sh_degree(degree), b.with_sh_degree(degree));
    a.append(&b);
    a
}

/// The document's buffers and the accessors decoded so far (shared accessors once).
pub(super) struct Ctx<'a> {
    pub(super) what: &'a str,
    buffers: Vec<Rc<Vec<u8>>>,
    /// Accessors without a buffer view of their own (from_bytes).
    dataless: HashSet<usize>,
    cache: RefCell<HashMap<usize, Rc<Vec<f32>>>>,
}

/// Which component types an attribute may have: (type, normalized).
fn allowed(name: &str) -> &'static [(DataType, bool)] {
    use DataType::*;
    match name {
        "POSITION" => &[
            (F32, false),
            (I8, false),
            (I8, true),
            (U8, false),
            (U8, true),
            (I16, false),
            (I16, true),
            (U16, false),
            (U16, true),
        ],
        "ROTATION" => &[(F32, false), (I8, true), (I16, true)],
        "SCALE" => &[(F32, false), (I8, false), (I8, true), (I16, false), (I16, true)],
        "OPACITY" => &[(F32, false), (U8, true), (U16, true)],
        _ => &[(F32, false)],
    }
}

impl Ctx<'_> {
    /// The accessor's values as f32 (normalized integers per glTF: signed c/max, at least −1;
    /// unsigned c/max), checked against `name`'s allowed types and `dims` components.
    pub(super) fn values(&self, acc: &gltf::Accessor, name: &str, dims: usize) -> Result<Rc<Vec<f32>>> {
        let what = self.what;
        let (dt, norm) = (acc.data_type(), acc.normalized());
        if !allowed(name).contains(&(dt, norm)) {
            bail!(
                "{what}: accessor {} ({name}) has component type {dt:?}{}, which {EXTENSION} does not allow there",
                acc.index(),
                if norm { " normalized" } else { "" }
            );
        }
        if acc.dimensions().multiplicity() != dims {
            bail!("{what}: accessor {} ({name}) is {:?}, not {dims} components", acc.index(), acc.dimensions());
        }
        if let Some(v) = self.cache.borrow().get(&acc.index()) {
            return Ok(v.clone());
        }
        if self.dataless.contains(&acc.index()) {
            bail!(
                "{what}: accessor {} ({name}) has no buffer view (data from an extension we do not read, or all zeros)",
                acc.index()
            );
        }
        if acc.sparse().is_some() {
            bail!("{what}: accessor {} ({name}) is sparse; sparse accessors are not read", acc.index());
        }
        let view = acc.view().ok_or_else(|| anyhow!("{what}: accessor {} ({name}) has no buffer view", acc.index()))?;
        let data = &self.buffers[view.buffer().index()];
        let elem = dims * dt.size();
        let stride = view.stride().unwrap_or(elem);
        let count = acc.count();
        let view_end = view.offset().checked_add(view.length()).filter(|&e| e <= data.len());
        let start = view.offset().checked_add(acc.offset());
        let end = count
            .checked_sub(1)
            .and_then(|c| c.checked_mul(stride))
            .and_then(|v| v.checked_add(elem))
            .and_then(|v| v.checked_add(start?));
        if stride < elem || view_end.is_none() || (count > 0 && end.is_none_or(|e| e > view_end.unwrap_or(0))) {
            bail!("{what}: accessor {} ({name}) reaches past its buffer view or buffer", acc.index());
        }
        let start = start.unwrap_or(0);
        let mut out = Vec::with_capacity(count * dims);
        for i in 0..count {
            let row = &data[start + i * stride..start + i * stride + elem];
            for d in 0..dims {
                out.push(component(row, d, dt, norm));
            }
        }
        let out = Rc::new(out);
        self.cache.borrow_mut().insert(acc.index(), out.clone());
        Ok(out)
    }

    /// The primitive's splats in glTF space before its node's transform.
    pub(super) fn primitive(&self, doc: &gltf::Document, p: &SplatPrimitive) -> Result<Scene> {
        let what = format!("{}: node {} primitive {}", self.what, p.node, p.primitive);
        let node = doc.nodes().nth(p.node).ok_or_else(|| anyhow!("{what}: no such node"))?;
        let prim = node
            .mesh()
            .and_then(|m| m.primitives().nth(p.primitive))
            .ok_or_else(|| anyhow!("{what}: no such primitive"))?;
        if prim.mode() != gltf::mesh::Mode::Points {
            bail!("{what}: a {EXTENSION} primitive must have mode POINTS (0), not {:?}", prim.mode());
        }
        let ext = prim.extensions().and_then(|e| e.get(EXTENSION)).cloned().unwrap_or(Value::Null);
        let linear = match ext.get("colorSpace") {
            None => false,
            Some(Value::String(s)) if s == "srgb_rec709_display" => false,
            Some(Value::String(s)) if s == "lin_rec709_display" => true,
            Some(other) => bail!(
                "{what}: {EXTENSION}.colorSpace {other} is not read (srgb_rec709_display and lin_rec709_display are)"
            ),
        };
        if let Some(spz) = ext.pointer(&format!("/extensions/{}", super::tiles::SPZ_EXTENSION)) {
            return self.spz_primitive(doc, &prim, spz, &what);
        }
        let mut attrs: HashMap<String, gltf::Accessor> = HashMap::new();
        for (sem, acc) in prim.attributes() {
            match sem {
                Semantic::Positions => {
                    attrs.insert("POSITION".into(), acc);
                }
                Semantic::Extras(n) if n.starts_with(PREFIX) => {
                    attrs.insert(n[PREFIX.len()..].to_string(), acc);
                }
                _ => {}
            }
        }
        let get = |name: &str, dims: usize| -> Result<Rc<Vec<f32>>> {
            let acc = attrs.get(name).ok_or_else(|| {
                anyhow!(
                    "{what}: no {} attribute (required)",
                    if name == "POSITION" { name.to_string() } else { format!("{PREFIX}{name}") }
                )
            })?;
            self.values(acc, name, dims)
        };
        let degree = sh_degree(&attrs, &what)?;
        let pos = get("POSITION", 3)?;
        let n = pos.len() / 3;
        let (rot, scale, alpha, dc) =
            (get("ROTATION", 4)?, get("SCALE", 3)?, get("OPACITY", 1)?, get("SH_DEGREE_0_COEF_0", 3)?);
        let rest: Vec<Rc<Vec<f32>>> = (1..((degree + 1) * (degree + 1)) as usize)
            .map(|k| get(&sh_name(k)[PREFIX.len()..], 3))
            .collect::<Result<_>>()?;
        if rot.len() != n * 4
            || scale.len() != n * 3
            || alpha.len() != n
            || dc.len() != n * 3
            || rest.iter().any(|r| r.len() != n * 3)
        {
            bail!("{what}: its attributes' counts differ");
        }
        let mut scene = scene_from_attributes(&what, degree, &pos, &rot, &scale, &alpha, &dc, &rest)?;
        if let Some(acc) = prim.indices() {
            let idx = self.indices(&acc, n, &what)?;
            scene = scene.select(&idx);
        }
        if linear {
            eprintln!(
                "note: {what}: colorSpace lin_rec709_display: colours converted to sRGB per splat (the extension blends the linear values and converts the image; where splats overlap translucently the two differ slightly)"
            );
            linear_to_srgb(&mut scene);
        }
        Ok(scene)
    }

    /// An SPZ-compressed primitive (`KHR_gaussian_splatting_compression_spz_2`): its splats
    /// decoded from the extension's buffer view (glTF space), as many as its POSITION accessor
    /// says (checked before decoding); its accessors hold no data of their own.
    fn spz_primitive(&self, doc: &gltf::Document, prim: &gltf::Primitive, spz: &Value, what: &str) -> Result<Scene> {
        let ext = super::tiles::SPZ_EXTENSION;
        let view = spz
            .get("bufferView")
            .and_then(Value::as_u64)
            .and_then(|v| doc.views().nth(usize::try_from(v).ok()?))
            .ok_or_else(|| {
                anyhow!(
                    "{what}: {ext}.bufferView {} names no buffer view",
                    spz.get("bufferView").unwrap_or(&Value::Null)
                )
            })?;
        let data = &self.buffers[view.buffer().index()];
        let bytes = view
            .offset()
            .checked_add(view.length())
            .and_then(|end| data.get(view.offset()..end))
            .ok_or_else(|| anyhow!("{what}: {ext}'s buffer view {} reaches past its buffer", view.index()))?;
        let count = prim
            .get(&Semantic::Positions)
            .map(|a| a.count())
            .ok_or_else(|| anyhow!("{what}: no POSITION attribute (required, with the SPZ data's count)"))?;
        if prim.indices().is_some() {
            bail!("{what}: an SPZ-compressed primitive with indices (the extension has none)");
        }
        crate::formats::spz::read_spz_in_gltf(&format!("{what}: {ext}"), bytes, count)
    }

    /// A POINTS primitive's `indices`: the vertices it draws, each below `n`.
    fn indices(&self, acc: &gltf::Accessor, n: usize, what: &str) -> Result<Vec<usize>> {
        let (dt, i) = (acc.data_type(), acc.index());
        if acc.dimensions() != gltf::accessor::Dimensions::Scalar
            || acc.normalized()
            || !matches!(dt, DataType::U8 | DataType::U16 | DataType::U32)
        {
            bail!(
                "{what}: indices accessor {i} must be unsigned SCALAR bytes, shorts or ints, not {:?} {dt:?}",
                acc.dimensions()
            );
        }
        if acc.sparse().is_some() || self.dataless.contains(&i) {
            bail!("{what}: indices accessor {i} is sparse or has no buffer view; neither is read");
        }
        let view = acc.view().ok_or_else(|| anyhow!("{what}: indices accessor {i} has no buffer view"))?;
        let data = &self.buffers[view.buffer().index()];
        let size = dt.size();
        let stride = view.stride().unwrap_or(size);
        let count = acc.count();
        let start = view.offset().checked_add(acc.offset());
        let view_end = view.offset().checked_add(view.length()).filter(|&e| e <= data.len());
        let end = count.checked_sub(1).and_then(|c| c.checked_mul(stride)).and_then(|v| v.checked_add(size + start?));
        let (Some(start), Some(view_end)) = (start, view_end) else {
            bail!("{what}: indices accessor {i} reaches past its buffer view or buffer");
        };
        if stride < size || (count > 0 && end.is_none_or(|e| e > view_end)) {
            bail!("{what}: indices accessor {i} reaches past its buffer view or buffer");
        }
        (0..count)
            .map(|k| {
                let b = &data[start + k * stride..start + k * stride + size];
                let v = match dt {
                    DataType::U8 => b[0] as usize,
                    DataType::U16 => u16::from_le_bytes([b[0], b[1]]) as usize,
                    _ => u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as usize,
                };
                if v >= n {
                    bail!("{what}: indices accessor {i} names vertex {v} at {k}; the primitive has {n}");
                }
                Ok(v)
            })
            .collect()
    }

    /// The primitive's splats placed by its node's world matrix (glTF space).
    pub(super) fn placed(&self, p: &SplatPrimitive, doc: &gltf::Document) -> Result<Scene> {
        let s = self.primitive(doc, p)?;
        if p.world == Mat4::IDENTITY {
            return Ok(s);
        }
        let x = Similarity::from_mat4(p.world, &format!("{}: node {}'s world matrix", self.what, p.node))?;
        Ok(place(s, x))
    }
}

/// Splats `s` placed by `x` (positions, rotations, scales, SH bands): the instance maths.
fn place(s: Scene, x: Similarity) -> Scene {
    let n = s.len();
    let one = InstancedScene {
        sh_degree: s.sh_degree,
        background: Scene { sh_degree: s.sh_degree, ..Scene::default() },
        groups: vec![Group {
            name: String::new(),
            template: s,
            instances: vec![Instance { id: String::new(), transform: x }],
            offsets: Offsets::zeros(n),
        }],
    };
    one.expand()
}

/// The highest SH degree whose coefficients are all present (lower degrees complete too).
fn sh_degree(attrs: &HashMap<String, gltf::Accessor>, what: &str) -> Result<u32> {
    let mut degree = 0;
    for l in 1..=3usize {
        let present = (0..=2 * l).filter(|n| attrs.contains_key(&format!("SH_DEGREE_{l}_COEF_{n}"))).count();
        if present == 0 {
            break;
        }
        if present != 2 * l + 1 {
            bail!("{what}: SH degree {l} is partly defined ({present} of {} coefficients); the extension requires whole degrees", 2 * l + 1);
        }
        degree = l as u32;
    }
    let limit = ((degree + 1) * (degree + 1)) as usize;
    let known = |k: &str| k == "SH_DEGREE_0_COEF_0" || (1..limit).any(|i| sh_name(i)[PREFIX.len()..] == *k);
    if let Some(k) = attrs.keys().find(|k| k.starts_with("SH_DEGREE_") && !known(k)) {
        bail!("{what}: attribute {PREFIX}{k} is beyond SH degree {degree} (degrees 0-3, each whole and every lower one present)");
    }
    Ok(degree)
}

/// Colours stored linear (`colorSpace` `lin_rec709_display`) brought to the sRGB-encoded
/// values we render and train in: each splat's base colour (0.5 + C0·DC, clamped to [0, 1])
/// encoded with the sRGB transfer function (IEC 61966-2-1), and its higher SH bands scaled by
/// that function's slope there (first order: a splat's view-dependent colour varies little
/// about its base colour).
fn linear_to_srgb(s: &mut Scene) {
    use crate::math::SH_C0_F32;
    let c = s.sh_coeffs() * 3;
    let encode = |v: f32| if v <= 0.003_130_8 { 12.92 * v } else { 1.055 * v.powf(1.0 / 2.4) - 0.055 };
    let slope = |v: f32| if v <= 0.003_130_8 { 12.92 } else { 1.055 / 2.4 * v.powf(1.0 / 2.4 - 1.0) };
    for i in 0..s.len() {
        for ch in 0..3 {
            let lin = (0.5 + SH_C0_F32 * s.sh[i * c + ch]).clamp(0.0, 1.0);
            s.sh[i * c + ch] = (encode(lin) - 0.5) / SH_C0_F32;
            let d = slope(lin.max(1e-4));
            for k in 1..c / 3 {
                s.sh[i * c + k * 3 + ch] *= d;
            }
        }
    }
}

/// One component of an accessor row.
fn component(row: &[u8], d: usize, dt: DataType, norm: bool) -> f32 {
    let at = d * dt.size();
    let b = &row[at..at + dt.size()];
    match dt {
        DataType::I8 => {
            let v = b[0] as i8 as f32;
            if norm {
                (v / 127.0).max(-1.0)
            } else {
                v
            }
        }
        DataType::U8 => {
            let v = b[0] as f32;
            if norm {
                v / 255.0
            } else {
                v
            }
        }
        DataType::I16 => {
            let v = i16::from_le_bytes([b[0], b[1]]) as f32;
            if norm {
                (v / 32767.0).max(-1.0)
            } else {
                v
            }
        }
        DataType::U16 => {
            let v = u16::from_le_bytes([b[0], b[1]]) as f32;
            if norm {
                v / 65535.0
            } else {
                v
            }
        }
        DataType::U32 => u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f32,
        DataType::F32 => f32::from_le_bytes([b[0], b[1], b[2], b[3]]),
    }
}

/// An opacity after the sigmoid as a logit (0 and 1: ±ln 1019).
fn logit(a: f32) -> f32 {
    if a <= 0.0 {
        -OPACITY_LOGIT_LIMIT
    } else if a >= 1.0 {
        OPACITY_LOGIT_LIMIT
    } else {
        crate::math::logit(a)
    }
}

/// A Scene (glTF space) from decoded attributes; refuses negative scales and opacities
/// outside [0, 1].
#[allow(clippy::too_many_arguments)]
fn scene_from_attributes(
    what: &str,
    degree: u32,
    pos: &[f32],
    rot: &[f32],
    scale: &[f32],
    alpha: &[f32],
    dc: &[f32],
    rest: &[Rc<Vec<f32>>],
) -> Result<Scene> {
    let n = pos.len() / 3;
    let c = ((degree + 1) * (degree + 1)) as usize;
    if let Some(i) = scale.iter().position(|v| *v < 0.0 || v.is_nan()) {
        bail!(
            "{what}: {PREFIX}SCALE of splat {} is {}; the extension stores linear scales ≥ 0 (a negative value is a log-space scale, the 2025 review draft's)",
            i / 3,
            scale[i]
        );
    }
    if let Some(i) = alpha.iter().position(|v| !(0.0..=1.0).contains(v)) {
        bail!("{what}: {PREFIX}OPACITY of splat {i} is {}; opacities after the sigmoid lie in [0, 1]", alpha[i]);
    }
    let mut sh = Vec::with_capacity(n * c * 3);
    for i in 0..n {
        sh.extend_from_slice(&dc[i * 3..i * 3 + 3]);
        for r in rest {
            sh.extend_from_slice(&r[i * 3..i * 3 + 3]);
        }
    }
    Ok(Scene {
        means: pos.chunks_exact(3).map(|p| [p[0], p[1], p[2]]).collect(),
        scales: scale
            .chunks_exact(3)
            .map(|s| s.iter().map(|v| v.max(f32::MIN_POSITIVE).ln()).collect::<Vec<_>>().try_into().unwrap_or([0.0; 3]))
            .collect(),
        quats: rot.chunks_exact(4).map(|q| [q[3], q[0], q[1], q[2]]).collect(),
        opacities: alpha.iter().map(|&a| logit(a)).collect(),
        sh,
        sh_degree: degree,
    })
}
