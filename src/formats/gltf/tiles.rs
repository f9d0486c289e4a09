//! 3D Tiles 1.1 tilesets of SPZ-compressed splats: the form CesiumJS draws splats in.
//!
//! `tileset.json` names one `.glb` per tile; each holds one node with one splat primitive whose
//! data is an SPZ blob (`KHR_gaussian_splatting` with `KHR_gaussian_splatting_compression_spz_2`,
//! both required by the glTF and, through `3DTILES_content_gltf`, by the tileset: CesiumJS
//! 1.145 draws splats only then, and only the first primitive of the first node). A plain
//! scene is one tile. An instanced scene is a background tile and one tile per instance, its
//! splats placed in the scene's frame: SPZ has no shared rows, so an instance's bytes are its
//! own either way, and CesiumJS 1.145 evaluates every tile's SH bands in the *first* selected
//! tile's frame (`GaussianSplatPrimitive`: "all tiles in a typical GS tileset share the same
//! root coordinate frame"), so a tile turned by its `transform` would show its view-dependent
//! colour from the wrong direction. The root's box holds every tile's.
//!
//! Frames: glTF content in 3D Tiles is y-up and turned to the tileset's z-up by a quarter
//! turn about x ((x, y, z) → (x, −z, y), the specification's rule); our frame goes to glTF's by
//! the half turn about z ([`super::half_turn_z`]). A point p of ours is the tileset's M·p with
//! M(x, y, z) = (−x, −z, −y), and a tile `transform` T (other tools' tilesets) is our
//! M⁻¹·T·M. The SPZ blob holds glTF's frame as it is, as CesiumJS reads it (not as the
//! extension's text asks: [`crate::formats::spz::spz_in_gltf`]).
use std::path::{Path, PathBuf};

use anyhow::{anyhow, bail, Context, Result};
use glam::{Mat3, Mat4, Vec3};
use serde_json::{json, Value};

use super::{bounds, extension_object, half_turn_z, sh_name, EXTENSION, PREFIX};
use crate::model::instanced::{transform_gaussians, InstancedScene, Similarity};
use crate::model::scene::Scene;

/// The SPZ compression extension inside `KHR_gaussian_splatting`.
pub const SPZ_EXTENSION: &str = "KHR_gaussian_splatting_compression_spz_2";

/// Our frame → the tileset's (module docs): columns are the images of x, y, z.
const TO_TILES: Mat3 = Mat3::from_cols(Vec3::new(-1.0, 0.0, 0.0), Vec3::new(0.0, 0.0, -1.0), Vec3::new(0.0, -1.0, 0.0));

/// Deepest tile tree and most tiles a tileset may have for us to read it.
const MAX_DEPTH: usize = 64;
const MAX_TILES: usize = 1 << 16;

/// Whether the JSON file at `path` (its first 64 MiB) is a 3D Tiles tileset: an object with
/// `asset` and `root`.
pub fn looks_like_tileset(path: &Path) -> bool {
    std::fs::File::open(path)
        .ok()
        .and_then(|f| {
            serde_json::from_reader::<_, Value>(std::io::BufReader::new(std::io::Read::take(f, 64 << 20))).ok()
        })
        .is_some_and(|v| v.get("asset").is_some() && v.get("root").is_some())
}

/// One tile's `.glb`: `s` (our frame) as one node with one SPZ-compressed splat primitive.
fn tile_glb(s: &Scene, what: &str) -> Result<Vec<u8>> {
    let n = s.len();
    let mut turned = s.clone();
    half_turn_z(&mut turned);
    let spz = crate::formats::spz::spz_in_gltf(&turned, what)?;
    // POSITION's bounds (glTF requires them), widened by SPZ's 1/4096 fixed-point step.
    let (lo, hi) = bounds(turned.means.iter().map(|m| Vec3::from(*m)));
    let step = 1.0 / 4096.0;
    let float = |ty: &str| json!({"componentType": 5126, "count": n, "type": ty});
    let mut accessors = vec![
        json!({"componentType": 5126, "count": n, "type": "VEC3",
               "min": (lo - step).to_array(), "max": (hi + step).to_array()}),
        json!({"componentType": 5121, "normalized": true, "count": n, "type": "VEC4"}),
        float("VEC3"),
        float("VEC4"),
    ];
    let mut attributes = serde_json::Map::new();
    attributes.insert("POSITION".into(), json!(0));
    attributes.insert("COLOR_0".into(), json!(1));
    attributes.insert(format!("{PREFIX}SCALE"), json!(2));
    attributes.insert(format!("{PREFIX}ROTATION"), json!(3));
    for k in 1..s.sh_coeffs() {
        attributes.insert(sh_name(k), json!(accessors.len()));
        accessors.push(float("VEC3"));
    }
    let mut ext = extension_object();
    ext["extensions"] = json!({SPZ_EXTENSION: {"bufferView": 0}});
    let doc = json!({
        "asset": {"version": "2.0", "generator": concat!("instgs-vk ", env!("CARGO_PKG_VERSION"))},
        "extensionsUsed": [EXTENSION, SPZ_EXTENSION],
        "extensionsRequired": [EXTENSION, SPZ_EXTENSION],
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": [{"attributes": attributes, "mode": 0, "extensions": {EXTENSION: ext}}]}],
        "buffers": [{"byteLength": spz.len()}],
        "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": spz.len()}],
        "accessors": accessors,
    });
    super::write::glb_bytes(&doc, spz, what)
}

/// The axis-aligned box (3D Tiles `box`: centre, then three half axes) from `lo` to `hi`, at
/// least 1e-6 thick.
fn bounding_box((lo, hi): (Vec3, Vec3)) -> Value {
    let (c, h) = ((lo + hi) * 0.5, ((hi - lo) * 0.5).max(Vec3::splat(1e-6)));
    json!([c.x, c.y, c.z, h.x, 0.0, 0.0, 0.0, h.y, 0.0, 0.0, 0.0, h.z])
}

/// Three standard deviations of the largest splat in `s`: how far a splat reaches past its mean.
fn reach(s: &Scene) -> f32 {
    3.0 * s.scales.iter().flatten().fold(f32::NEG_INFINITY, |a, &v| a.max(v)).exp()
}

/// Writes a plain scene as a tileset of one tile: `out` (its `tileset.json`) and `tile-0.glb`
/// beside it.
pub fn write_tileset(scene: &Scene, out: &Path) -> Result<()> {
    write_tiles(vec![scene.clone()], out)
}

/// Writes an instanced scene as a tileset: `out` and, beside it, a background tile and a tile
/// per instance in the scene's frame (`tile-0.glb`, … in the order the tileset lists them).
pub fn write_instanced_tileset(scene: &InstancedScene, out: &Path) -> Result<()> {
    scene.validate(&out.display().to_string())?;
    let mut tiles: Vec<Scene> = Vec::new();
    if !scene.background.is_empty() {
        tiles.push(scene.background.clone());
    }
    for (g, group) in scene.groups.iter().enumerate() {
        for (k, inst) in group.instances.iter().enumerate() {
            tiles.push(transform_gaussians(&scene.instance_in_template_frame(g, k), &inst.transform));
        }
    }
    write_tiles(tiles, out)
}

/// The tiles (content in our frame) and their tileset. Nothing is left half-written: on an
/// error the tiles already written are removed and no `tileset.json` is written.
fn write_tiles(tiles: Vec<Scene>, out: &Path) -> Result<()> {
    let what = out.display().to_string();
    let dir = out.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
    std::fs::create_dir_all(dir).with_context(|| format!("{what}: cannot create its folder"))?;
    let mut written: Vec<PathBuf> = Vec::new();
    let result = (|| -> Result<Value> {
        let mut children = Vec::new();
        let (mut lo, mut hi) = (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY));
        for (i, content) in tiles.iter().enumerate() {
            let name = format!("tile-{i}.glb");
            let path = dir.join(&name);
            let bytes = tile_glb(content, &format!("{what}: {name}"))?;
            crate::util::write_atomic(&path, |f| std::io::Write::write_all(f, &bytes))?;
            written.push(path);
            let (a, b) = bounds(content.means.iter().map(|m| TO_TILES * Vec3::from(*m)));
            let pad = Vec3::splat(reach(content));
            (lo, hi) = (lo.min(a - pad), hi.max(b + pad));
            children.push(json!({
                "boundingVolume": {"box": bounding_box((a - pad, b + pad))},
                "geometricError": 0.0,
                "content": {"uri": name},
            }));
        }
        let (root_box, diagonal) = (bounding_box((lo, hi)), (hi - lo).length().max(1e-6));
        let extensions = json!([EXTENSION, SPZ_EXTENSION]);
        Ok(json!({
            "asset": {"version": "1.1", "generator": concat!("instgs-vk ", env!("CARGO_PKG_VERSION"))},
            "extensionsUsed": ["3DTILES_content_gltf"],
            "extensionsRequired": ["3DTILES_content_gltf"],
            "extensions": {"3DTILES_content_gltf": {"extensionsUsed": extensions, "extensionsRequired": extensions}},
            "geometricError": diagonal,
            "root": {
                "boundingVolume": {"box": root_box},
                "geometricError": diagonal,
                "refine": "ADD",
                "children": children,
            },
        }))
    })();
    let tileset = match result {
        Ok(t) => t,
        Err(e) => {
            for p in &written {
                let _ = std::fs::remove_file(p);
            }
            return Err(e);
        }
    };
    let text = serde_json::to_string_pretty(&tileset)?;
    crate::util::write_atomic(out, |f| std::io::Write::write_all(f, text.as_bytes()))
}

/// Reads a tileset as one plain scene: every tile's glTF content (read as any glTF we read,
/// SPZ-compressed or not; only files inside the tileset's folder, [`crate::limits::confined`])
/// placed by its tiles' transforms, in our frame. Refused: transforms that are not similarities,
/// tile trees deeper than 64 or with more than 65 536 tiles, content other than glTF, and a
/// total past the memory budget.
pub fn read_tileset(path: &Path) -> Result<Scene> {
    let what = path.display().to_string();
    let bytes = crate::limits::read_limited(path, &what, "the tileset", 64 << 20, true)?;
    let doc: Value =
        serde_json::from_slice(&bytes).map_err(|e| anyhow!("{what}: the tileset JSON does not parse: {e}"))?;
    let version = doc.pointer("/asset/version").and_then(Value::as_str).unwrap_or("");
    if !version.starts_with("1.") {
        bail!("{what}: asset.version {version:?}: a 3D Tiles 1.x tileset was expected");
    }
    let root = doc.get("root").ok_or_else(|| anyhow!("{what}: no root tile"))?;
    let to_tiles = Mat4::from_mat3(TO_TILES);
    let mut scene = Scene::default();
    let mut stack = vec![(root, Mat4::IDENTITY, 0usize, "root".to_string())];
    let mut tiles = 0usize;
    while let Some((tile, parent, depth, name)) = stack.pop() {
        tiles += 1;
        if depth > MAX_DEPTH || tiles > MAX_TILES {
            bail!("{what}: the tile tree is deeper than {MAX_DEPTH} or has more than {MAX_TILES} tiles");
        }
        let local = match tile.get("transform") {
            None => Mat4::IDENTITY,
            Some(t) => {
                let v: Vec<f32> = t
                    .as_array()
                    .filter(|a| a.len() == 16)
                    .map(|a| a.iter().filter_map(|x| x.as_f64().map(|f| f as f32)).collect())
                    .unwrap_or_default();
                if v.len() != 16 {
                    bail!("{what}: {name}'s transform is not 16 numbers");
                }
                Mat4::from_cols_slice(&v)
            }
        };
        let world = parent * local;
        if let Some(content) = tile.get("content") {
            let uri = content
                .get("uri")
                .or_else(|| content.get("url"))
                .and_then(Value::as_str)
                .ok_or_else(|| anyhow!("{what}: {name}'s content has no uri"))?;
            let field = format!("{name}'s content uri");
            let file = crate::limits::confined(path, &field, uri)?;
            let s = match super::read(&file).with_context(|| format!("{what}: {field} {uri:?}"))? {
                super::GltfScene::Plain(s) => s,
                super::GltfScene::Instanced(s) => s.expand(),
            };
            // The tile's transform in our frame: M⁻¹·T·M (module docs).
            let x =
                Similarity::from_mat4(to_tiles.transpose() * world * to_tiles, &format!("{what}: {name}'s transform"))?;
            let placed = if world == Mat4::IDENTITY { s } else { transform_gaussians(&s, &x) };
            let total = (scene.len() + placed.len()) as u64;
            crate::limits::check_bytes(
                &what,
                &format!("its tiles' {total} splats"),
                total.saturating_mul(super::read::BYTES_PER_SPLAT),
            )?;
            scene = super::read::append_any_degree(scene, placed);
        }
        if let Some(children) = tile.get("children").and_then(Value::as_array) {
            for (i, c) in children.iter().enumerate().rev() {
                stack.push((c, world, depth + 1, format!("{name}.children[{i}]")));
            }
        }
    }
    if scene.is_empty() {
        bail!("{what}: a tileset without splat content");
    }
    scene.validate(&what)?;
    Ok(scene)
}
