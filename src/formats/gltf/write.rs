//! Writing glTF: plain scenes (one splat primitive) and instanced scenes (templates shared).
use std::path::Path;

use anyhow::{anyhow, bail, Context, Result};
use serde_json::{json, Map, Value};

use super::{
    extension_object, half_turn_z, sh_name, turn_similarity, Accessors, Dequantise, GroupExtras, InstanceExtras,
    InstgsExtras, EXTENSION, EXTRAS_VERSION, MESH_QUANTIZATION, PREFIX, TEMPLATE_DC, TEMPLATE_OPACITY_LOGIT,
    TEMPLATE_POSITION,
};
use crate::formats::quant::snorm16;
use crate::math::sigmoid;
use crate::model::instanced::{InstancedScene, Similarity};
use crate::model::scene::Scene;

/// The BIN chunk, its buffer views and accessors as they are built.
#[derive(Default)]
struct Builder {
    bin: Vec<u8>,
    views: Vec<Value>,
    accessors: Vec<Value>,
}

impl Builder {
    /// One tightly packed accessor of `values` (`ty`: SCALAR, VEC3, VEC4); min/max on request
    /// (glTF requires them on POSITION).
    fn floats(&mut self, values: &[f32], ty: &str, dims: usize, bounds: bool) -> usize {
        let mut acc = json!({"componentType": 5126, "count": values.len() / dims, "type": ty});
        if bounds {
            let (mut lo, mut hi) = (vec![f32::INFINITY; dims], vec![f32::NEG_INFINITY; dims]);
            for row in values.chunks_exact(dims) {
                for d in 0..dims {
                    lo[d] = lo[d].min(row[d]);
                    hi[d] = hi[d].max(row[d]);
                }
            }
            acc["min"] = json!(lo);
            acc["max"] = json!(hi);
        }
        self.push(bytemuck::cast_slice(values), acc)
    }

    /// POSITION: floats, or under `d` normalized signed shorts, each row padded to 8 bytes
    /// (a vertex attribute's rows align to 4), min/max in the stored integers.
    fn positions(&mut self, means: &[[f32; 3]], d: Option<&Dequantise>) -> usize {
        let Some(d) = d else { return self.floats(&means.concat(), "VEC3", 3, true) };
        let (mut lo, mut hi) = ([i16::MAX; 3], [i16::MIN; 3]);
        let mut bytes = Vec::with_capacity(means.len() * 8);
        for m in means {
            let q = d.quantise(*m);
            for a in 0..3 {
                (lo[a], hi[a]) = (lo[a].min(q[a]), hi[a].max(q[a]));
                bytes.extend_from_slice(&q[a].to_le_bytes());
            }
            bytes.extend_from_slice(&[0, 0]);
        }
        let acc = json!({"componentType": 5122, "normalized": true, "count": means.len(), "type": "VEC3", "min": lo, "max": hi});
        let i = self.push(&bytes, acc);
        // `push` wrote this accessor's view last.
        if let Some(view) = self.views.last_mut() {
            view["byteStride"] = json!(8);
        }
        i
    }

    fn push(&mut self, bytes: &[u8], mut acc: Value) -> usize {
        let offset = self.bin.len();
        self.bin.extend_from_slice(bytes);
        while !self.bin.len().is_multiple_of(4) {
            self.bin.push(0);
        }
        self.views.push(json!({"buffer": 0, "byteOffset": offset, "byteLength": bytes.len(), "target": 34962}));
        acc["bufferView"] = json!(self.views.len() - 1);
        self.accessors.push(acc);
        self.accessors.len() - 1
    }
}

/// SH coefficient `k` (RGB) of every splat, in splat order (k = 0: the DC term).
fn coefficient(s: &Scene, k: usize) -> Vec<f32> {
    let c = s.sh_coeffs();
    (0..s.len()).flat_map(|i| s.sh[(i * c + k) * 3..(i * c + k) * 3 + 3].iter().copied()).collect()
}

/// Accessors of the rows every instance of a template shares: ROTATION, SCALE, SH rest.
struct Shared {
    rotation: usize,
    scale: usize,
    sh_rest: Vec<usize>,
}

/// Writes `s`'s (glTF frame) rotations, linear scales and SH rest coefficients; under `d`
/// the rotations as normalized signed shorts and the scales divided by its scale (the node's
/// scale multiplies them back).
fn shared_accessors(b: &mut Builder, s: &Scene, d: Option<&Dequantise>) -> Shared {
    // Unit quaternions (the extension's requirement; ours need not be normalised).
    let rot: Vec<f32> = s
        .quats
        .iter()
        .flat_map(|q| {
            let n = q.iter().map(|v| v * v).sum::<f32>().sqrt();
            [q[1] / n, q[2] / n, q[3] / n, q[0] / n]
        })
        .collect();
    let rotation = match d {
        None => b.floats(&rot, "VEC4", 4, false),
        Some(_) => {
            let q: Vec<i16> = rot.iter().map(|&v| snorm16(v)).collect();
            b.push(
                bytemuck::cast_slice(&q),
                json!({"componentType": 5122, "normalized": true, "count": s.len(), "type": "VEC4"}),
            )
        }
    };
    let node_scale = d.map_or(1.0, |d| d.scale);
    let scale: Vec<f32> = s.scales.iter().flatten().map(|v| v.exp() / node_scale).collect();
    let c = s.sh_coeffs();
    let sh_rest = (1..c).map(|k| b.floats(&coefficient(s, k), "VEC3", 3, false)).collect();
    Shared { rotation, scale: b.floats(&scale, "VEC3", 3, false), sh_rest }
}

/// Writes `s`'s own attributes (POSITION, under `d` quantised; OPACITY, DC, COLOR_0) and
/// returns the primitive with `shared` for the rest.
fn primitive(b: &mut Builder, s: &Scene, shared: &Shared, d: Option<&Dequantise>) -> Value {
    let alpha: Vec<f32> = s.opacities.iter().map(|&o| sigmoid(o)).collect();
    let dc = coefficient(s, 0);
    let colour: Vec<u8> = (0..s.len())
        .flat_map(|i| {
            let rgb =
                dc[i * 3..i * 3 + 3].iter().map(|&v| crate::formats::quant::unorm8(v * crate::math::SH_C0_F32 + 0.5));
            rgb.chain([crate::formats::quant::unorm8(alpha[i])]).collect::<Vec<u8>>()
        })
        .collect();
    let mut attributes = Map::new();
    attributes.insert("POSITION".into(), json!(b.positions(&s.means, d)));
    let colour = b.push(&colour, json!({"componentType": 5121, "normalized": true, "count": s.len(), "type": "VEC4"}));
    attributes.insert("COLOR_0".into(), json!(colour));
    attributes.insert(format!("{PREFIX}ROTATION"), json!(shared.rotation));
    attributes.insert(format!("{PREFIX}SCALE"), json!(shared.scale));
    attributes.insert(format!("{PREFIX}OPACITY"), json!(b.floats(&alpha, "SCALAR", 1, false)));
    attributes.insert(format!("{PREFIX}SH_DEGREE_0_COEF_0"), json!(b.floats(&dc, "VEC3", 3, false)));
    for (k, &a) in shared.sh_rest.iter().enumerate() {
        attributes.insert(sh_name(k + 1), json!(a));
    }
    json!({"attributes": attributes, "mode": 0, "extensions": {EXTENSION: extension_object()}})
}

/// A whole plain scene's primitive (in our frame; turned here) and its node (a dequantising
/// translation and scale with quantised positions; refused where that node's scale is past what
/// the readers take of a node, as an instance's node is).
fn plain_primitive(b: &mut Builder, scene: &Scene, accessors: Accessors) -> Result<(Value, Map<String, Value>)> {
    let mut s = scene.clone();
    half_turn_z(&mut s);
    let d = (accessors == Accessors::Quantized).then(|| Dequantise::of(&s.means));
    if let Some(d) = &d {
        Similarity::from_mat4(d.mat4(), "quantised positions: their node (half their largest side)")
            .map_err(|e| anyhow!("{e}; write float positions (without --quantize)"))?;
    }
    let shared = shared_accessors(b, &s, d.as_ref());
    let mut node = Map::new();
    if let Some(d) = &d {
        node.insert("translation".into(), json!(d.translation));
        node.insert("scale".into(), json!([d.scale, d.scale, d.scale]));
    }
    Ok((primitive(b, &s, &shared, d.as_ref()), node))
}

/// The document around `nodes` (all roots of scene 0) and `meshes`.
fn document(b: &Builder, nodes: Vec<Value>, meshes: Vec<Value>, extras: Option<Value>, accessors: Accessors) -> Value {
    let roots: Vec<usize> = (0..nodes.len()).collect();
    let mut doc = json!({
        "asset": {"version": "2.0", "generator": concat!("instgs-vk ", env!("CARGO_PKG_VERSION"))},
        "extensionsUsed": [EXTENSION],
        "scene": 0,
        "scenes": [{"nodes": roots}],
        "nodes": nodes,
        "meshes": meshes,
        "buffers": [{"byteLength": b.bin.len()}],
        "bufferViews": b.views,
        "accessors": b.accessors,
    });
    if let Some(e) = extras {
        doc["extras"] = e;
    }
    if accessors == Accessors::Quantized {
        doc["extensionsUsed"] = json!([EXTENSION, MESH_QUANTIZATION]);
        doc["extensionsRequired"] = json!([MESH_QUANTIZATION]);
    }
    doc
}

/// Writes the document: `.gltf` as JSON with the buffer as a base64 `data:` URI, anything else
/// as GLB (JSON and BIN chunks).
fn write_document(mut doc: Value, bin: Vec<u8>, out: &Path) -> Result<()> {
    let name = out.file_name().map(|n| n.to_string_lossy().to_ascii_lowercase()).unwrap_or_default();
    let bytes = if name.ends_with(".gltf") {
        doc["buffers"][0]["uri"] = json!(format!("data:application/octet-stream;base64,{}", base64::encode(&bin)));
        serde_json::to_vec(&doc)?
    } else {
        glb_bytes(&doc, bin, &out.display().to_string())?
    };
    crate::util::write_atomic(out, |f| std::io::Write::write_all(f, &bytes))
}

/// The document and its buffer as GLB bytes (JSON and BIN chunks); `what` names the file.
pub(super) fn glb_bytes(doc: &Value, bin: Vec<u8>, what: &str) -> Result<Vec<u8>> {
    let json = serde_json::to_vec(doc)?;
    if json.len() as u64 + bin.len() as u64 + 64 > u32::MAX as u64 {
        bail!("{what}: a GLB holds at most 4 GiB; this scene needs {} bytes", json.len() + bin.len());
    }
    let header = gltf::binary::Header { magic: *b"glTF", version: 2, length: 0 };
    let glb = gltf::binary::Glb { header, json: json.into(), bin: Some(bin.into()) };
    glb.to_vec().map_err(|e| anyhow!("{what}: {e}"))
}

/// Writes a plain scene as `.glb` (or `.gltf`, the buffer embedded): one node, one splat
/// primitive, its attributes as `accessors` says.
pub fn write_gltf(scene: &Scene, out: &Path, accessors: Accessors) -> Result<()> {
    scene.validate(&out.display().to_string())?;
    let mut b = Builder::default();
    let (prim, mut node) = plain_primitive(&mut b, scene, accessors).with_context(|| out.display().to_string())?;
    node.insert("mesh".into(), json!(0));
    let doc = document(&b, vec![Value::Object(node)], vec![json!({"primitives": [prim]})], None, accessors);
    write_document(doc, b.bin, out)
}

/// Writes an instanced scene with its templates shared (module docs), its attributes as
/// `accessors` says: quantised, each group's positions (its instances' own rows in template
/// space) share one dequantisation, which each instance's node applies after its transform.
pub fn write_instanced_gltf(scene: &InstancedScene, out: &Path, accessors: Accessors) -> Result<()> {
    scene.validate(&out.display().to_string())?;
    let mut b = Builder::default();
    let (mut nodes, mut meshes) = (Vec::new(), Vec::new());
    let mut extras = InstgsExtras { version: EXTRAS_VERSION, background: Vec::new(), groups: Vec::new() };
    if !scene.background.is_empty() {
        let (prim, mut node) =
            plain_primitive(&mut b, &scene.background, accessors).with_context(|| out.display().to_string())?;
        meshes.push(json!({"name": "background", "primitives": [prim]}));
        node.insert("name".into(), json!("background"));
        node.insert("mesh".into(), json!(0));
        nodes.push(Value::Object(node));
        extras.background.push(0);
    }
    for (gi, g) in scene.groups.iter().enumerate() {
        let mut t = g.template.clone();
        half_turn_z(&mut t);
        // Its instances' own rows in the template's frame, turned like the template's
        // (rotations, scales and higher SH bands are the template's: shared).
        let own: Vec<Scene> = (0..g.instances.len())
            .map(|k| {
                let mut own = scene.instance_in_template_frame(gi, k);
                half_turn_z(&mut own);
                own
            })
            .collect();
        let d = (accessors == Accessors::Quantized)
            .then(|| Dequantise::of(&own.iter().flat_map(|o| o.means.iter().copied()).collect::<Vec<_>>()));
        let shared = shared_accessors(&mut b, &t, d.as_ref());
        let mut group = GroupExtras { name: g.name.clone(), dequantise: d, instances: Vec::new() };
        for (k, (inst, own)) in g.instances.iter().zip(&own).enumerate() {
            let mut node_x = turn_similarity(&inst.transform)?;
            if let Some(d) = &d {
                node_x = Similarity::from_mat4(node_x.render_mat4() * d.mat4(), "an instance's node")?;
            }
            let r = node_x.rotation;
            let mut prim = primitive(&mut b, own, &shared, d.as_ref());
            if k == 0 {
                // The template's own rows, on the first instance (module docs).
                prim["attributes"][TEMPLATE_POSITION] = json!(b.floats(&t.means.concat(), "VEC3", 3, false));
                prim["attributes"][TEMPLATE_OPACITY_LOGIT] = json!(b.floats(&t.opacities, "SCALAR", 1, false));
                prim["attributes"][TEMPLATE_DC] = json!(b.floats(&coefficient(&t, 0), "VEC3", 3, false));
            }
            meshes.push(json!({"name": g.name, "primitives": [prim]}));
            nodes.push(json!({
                "name": inst.id,
                "mesh": meshes.len() - 1,
                "translation": node_x.translation.to_array(),
                "rotation": [r.x, r.y, r.z, r.w],
                "scale": [node_x.scale, node_x.scale, node_x.scale],
            }));
            group.instances.push(InstanceExtras { id: inst.id.clone(), node: nodes.len() - 1 });
        }
        extras.groups.push(group);
    }
    let doc = document(&b, nodes, meshes, Some(json!({"instgs": extras})), accessors);
    write_document(doc, b.bin, out)
}
