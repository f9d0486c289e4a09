//! glTF 2.0 with `KHR_gaussian_splatting` (`.glb`, `.gltf`): plain scenes read and written;
//! instanced scenes written with their templates shared and read back as the same instanced
//! scene. The container (GLB chunks, the document's types and validation, buffers in the BIN
//! chunk, `data:` URIs or files beside a `.gltf`) is the `gltf` crate's; this module maps the
//! splat attributes.
//!
//! # Conventions
//! Source: the extension's text (KhronosGroup/glTF, `extensions/2.0/Khronos/KHR_gaussian_splatting`)
//! with glTF/issues #2563 (SCALE made linear), and splat-transform 3.7.0's `.glb` writer, the
//! reference implementation we check against (`tools/interop.sh`).
//! - A splat primitive has `mode` POINTS (0) and the `KHR_gaussian_splatting` object
//!   (written: kernel `ellipse`, colorSpace `srgb_rec709_display`, projection `perspective`,
//!   sortingMethod `cameraDistance`). Other primitives are not splats and are skipped.
//! - Frame: glTF is right-handed, +Y up, +Z forward (so +X is left). Our scenes are in the
//!   Inria/COLMAP PLY frame (x right, y down, z forward), which a half turn about z maps to glTF:
//!   (x, y, z) → (−x, −y, z), quaternions q ↦ q_z(180°)·q, and SH coefficient (l, m) times
//!   (−1)^m (its basis function's parity in x and y). splat-transform applies the same turn
//!   (its PLY space is Euler (0, 0, 180°)). The turn is its own inverse.
//! - `POSITION` VEC3; `KHR_gaussian_splatting:ROTATION` VEC4 (x, y, z, w), ours (w, x, y, z);
//!   `:SCALE` VEC3 **linear** and ≥ 0 (ours: natural-log scales; a negative value, which only a
//!   log-space writer of the 2025 review draft produces, is refused naming that);
//!   `:OPACITY` SCALAR after the sigmoid, in [0, 1] (ours: logits; 0 and 1 read as
//!   ±ln 1019, as every reader of ours does); `:SH_DEGREE_0_COEF_0` VEC3 (r, g, b), the Inria
//!   `f_dc`; `:SH_DEGREE_l_COEF_n` (l = 1..3, n = 0..2l) the Inria rest coefficient
//!   k = l² + n (m = n − l), real SH with the Condon–Shortley phase as Inria's renderer
//!   evaluates them, so no sign changes beyond the frame's. `COLOR_0` (8-bit sRGB of the DC
//!   term and the opacity) is written for viewers without the extension and ignored on reading.
//! - Quantised accessors are read where the extension allows them: ROTATION as normalized
//!   signed bytes or shorts; SCALE as signed bytes or shorts, normalized or not; OPACITY as
//!   normalized unsigned bytes or shorts; POSITION as any integer type `KHR_mesh_quantization`
//!   allows (the node's matrix dequantises). SH is float. Sparse accessors are refused.
//!   We write floats (the extension's advice for precision), or with [`Accessors::Quantized`]
//!   (`convert --quantize`) 16-bit POSITION and ROTATION.
//! - Node transforms place splat primitives: the node's world matrix must be a similarity
//!   (rotation, uniform scale > 0, translation); positions take the matrix, rotations its
//!   rotation, log-scales its ln s, and SH bands are rotated by its rotation (the same maths as
//!   an instance's, [`InstancedScene::expand`]). A shear, a non-uniform scale or a mirror is
//!   refused: a Gaussian under them is no longer one of ours per splat row.
//!
//! # Instanced scenes
//! Each group's template rows that every instance shares — ROTATION, SCALE and the SH bands
//! above the DC term — are accessors written once. Each instance is a node (TRS: translation,
//! rotation, uniform scale: the template→world similarity conjugated by the frame's half turn,
//! exact up to f32) whose mesh has one splat primitive pointing at the shared accessors and at
//! its own POSITION (template means + the instance's Δp brought into template space:
//! μ + R⁻¹Δp/s), OPACITY (sigmoid of logit + Δo), SH_DEGREE_0_COEF_0 (DC + Δc) and COLOR_0. The
//! background is one more node. A viewer renders it right when it honours node transforms on
//! splat primitives as above — including the SH rotation, without which view-dependent colour
//! of a turned instance is evaluated in the wrong direction (its DC colour stays right).
//! Each template's own means, opacity logits and DC (float, glTF frame, template space) are
//! three application-specific attributes of its first instance's primitive
//! (`_INSTGS_TEMPLATE_POSITION`, …: the "_" names of glTF 2.0 §3.7.2.1, which viewers ignore), so
//! every accessor of the file is one a primitive of its scene uses. Root `extras.instgs` names
//! the groups and their instances' nodes, so a reader gets templates, transforms and offsets
//! back; a file whose extras do not match its nodes is read as a plain scene (said on stderr).
mod buffers;
mod instanced;
mod read;
mod tiles;
mod write;

use anyhow::Result;
use glam::{Mat4, Vec3};
use serde::{Deserialize, Serialize};
use serde_json::{json, Value};

use crate::model::instanced::{InstancedScene, Similarity};
use crate::model::scene::Scene;

pub use read::{from_bytes, looks_like_gltf, read};

/// What a glTF file holds: a plain scene, or the instanced scene our extras describe.
pub enum GltfScene {
    Plain(Scene),
    Instanced(InstancedScene),
}
pub use tiles::{looks_like_tileset, read_tileset, write_instanced_tileset, write_tileset, SPZ_EXTENSION};
pub use write::{write_gltf, write_instanced_gltf};
/// `KHR_mesh_quantization`: required by files with [`Accessors::Quantized`].
pub(crate) const MESH_QUANTIZATION: &str = "KHR_mesh_quantization";

/// The extension's name (on the primitive and in `extensionsUsed`).
pub const EXTENSION: &str = "KHR_gaussian_splatting";
/// Attribute names' prefix.
pub(crate) const PREFIX: &str = "KHR_gaussian_splatting:";
/// An instanced group's template means (glTF frame, template space), on its first instance's
/// primitive (module docs).
pub(crate) const TEMPLATE_POSITION: &str = "_INSTGS_TEMPLATE_POSITION";
/// … its opacity logits.
pub(crate) const TEMPLATE_OPACITY_LOGIT: &str = "_INSTGS_TEMPLATE_OPACITY_LOGIT";
/// … its DC terms.
pub(crate) const TEMPLATE_DC: &str = "_INSTGS_TEMPLATE_SH_DEGREE_0_COEF_0";
/// The three, the only application-specific attributes we read.
pub(crate) const TEMPLATE_ATTRIBUTES: [&str; 3] = [TEMPLATE_POSITION, TEMPLATE_OPACITY_LOGIT, TEMPLATE_DC];
/// The `extras.instgs` version we write and read (1, until 2026-11-27, named the template's
/// rows as accessors only the extras used).
pub(crate) const EXTRAS_VERSION: u32 = 2;
/// `extensionsRequired` entries we read; any other is refused.
pub(crate) const KNOWN_REQUIRED: [&str; 3] = [EXTENSION, MESH_QUANTIZATION, tiles::SPZ_EXTENSION];
/// The primitive's extension object we write.
pub(crate) fn extension_object() -> Value {
    json!({"kernel": "ellipse", "colorSpace": "srgb_rec709_display", "projection": "perspective", "sortingMethod": "cameraDistance"})
}

/// Sign of SH coefficient k (0..16, DC first, m = −l..l) under the half turn about z: (−1)^m.
const SH_HALF_TURN_Z: [f32; 16] =
    [1.0, -1.0, 1.0, -1.0, 1.0, -1.0, 1.0, -1.0, 1.0, -1.0, 1.0, -1.0, 1.0, -1.0, 1.0, -1.0];

/// The half turn about z between our PLY frame and glTF's (its own inverse).
pub fn half_turn_z(s: &mut Scene) {
    let c = s.sh_coeffs();
    for m in &mut s.means {
        m[0] = -m[0];
        m[1] = -m[1];
    }
    for q in &mut s.quats {
        let [w, x, y, z] = *q;
        *q = [-z, -y, x, w];
    }
    for (i, v) in s.sh.iter_mut().enumerate() {
        *v *= SH_HALF_TURN_Z[(i / 3) % c];
    }
}

/// A similarity conjugated by the half turn (either way).
pub(crate) fn turn_similarity(x: &Similarity) -> Result<Similarity> {
    let f = Mat4::from_scale(Vec3::new(-1.0, -1.0, 1.0));
    Similarity::from_mat4(f * x.render_mat4() * f, "a transform")
}

/// The SH rest coefficient k ≥ 1's attribute name.
pub(crate) fn sh_name(k: usize) -> String {
    let l = (k as f64).sqrt().floor() as usize;
    format!("{PREFIX}SH_DEGREE_{l}_COEF_{}", k - l * l)
}

/// How a writer stores the splat attributes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Accessors {
    /// Every attribute float32 (the extension's advice for precision).
    Float,
    /// POSITION as normalized signed shorts (`KHR_mesh_quantization`, required) dequantised by
    /// the node's translation and uniform scale, ROTATION as normalized signed
    /// shorts; SCALE (linear, divided by the node's scale), OPACITY, SH and the DC term stay
    /// float: the extension allows no integer SH, and a vertex attribute's rows align to 4
    /// bytes, so a 1- or 2-byte OPACITY would take a float's space. A short spends 1/65 534 of
    /// the bounding box's largest side per position axis (docs/formats.md).
    Quantized,
}

/// A dequantisation of positions: `POSITION = translation + scale · q`, q ∈ [−1, 1]³ the
/// normalized signed shorts; the node's transform (translation, uniform scale) in the file.
#[derive(Serialize, Deserialize, Clone, Copy, Debug, PartialEq)]
pub(crate) struct Dequantise {
    pub(crate) translation: [f32; 3],
    pub(crate) scale: f32,
}

impl Dequantise {
    /// The bounding box of `means`: its centre, half its largest side (at least 1e-6).
    pub(crate) fn of(means: &[[f32; 3]]) -> Dequantise {
        if means.is_empty() {
            return Dequantise { translation: [0.0; 3], scale: 1.0 };
        }
        let (lo, hi) = bounds(means.iter().map(|m| Vec3::from(*m)));
        Dequantise { translation: ((lo + hi) / 2.0).to_array(), scale: ((hi - lo).max_element() / 2.0).max(1e-6) }
    }

    pub(crate) fn mat4(&self) -> Mat4 {
        Mat4::from_translation(Vec3::from(self.translation)) * Mat4::from_scale(Vec3::splat(self.scale))
    }

    /// A position as normalized signed shorts.
    pub(crate) fn quantise(&self, p: [f32; 3]) -> [i16; 3] {
        std::array::from_fn(|a| crate::formats::quant::snorm16((p[a] - self.translation[a]) / self.scale))
    }

    /// Refuses what no writer of ours writes: a scale that is not finite and positive, a
    /// translation that is not finite.
    pub(crate) fn check(&self) -> Result<()> {
        if !(self.scale.is_finite() && self.scale > 0.0 && self.translation.iter().all(|v| v.is_finite())) {
            anyhow::bail!("dequantisation {:?} is not a finite translation and a positive scale", self);
        }
        Ok(())
    }
}

/// The smallest and largest coordinates of `points`.
pub(crate) fn bounds(points: impl Iterator<Item = Vec3>) -> (Vec3, Vec3) {
    points.fold((Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY)), |(lo, hi), p| (lo.min(p), hi.max(p)))
}

/// Root `extras.instgs`: what a reader needs to get the instanced scene back.
#[derive(Serialize, Deserialize)]
pub(crate) struct InstgsExtras {
    pub(crate) version: u32,
    /// Nodes of the background's primitives.
    pub(crate) background: Vec<usize>,
    pub(crate) groups: Vec<GroupExtras>,
}

#[derive(Serialize, Deserialize)]
pub(crate) struct GroupExtras {
    pub(crate) name: String,
    /// With quantised positions ([`Accessors::Quantized`]): the dequantisation every instance's
    /// node applies after its transform (its node's matrix is transform · dequantisation).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub(crate) dequantise: Option<Dequantise>,
    /// The first instance's primitive also holds the template's own rows ([`TEMPLATE_POSITION`]).
    pub(crate) instances: Vec<InstanceExtras>,
}

#[derive(Serialize, Deserialize)]
pub(crate) struct InstanceExtras {
    pub(crate) id: String,
    pub(crate) node: usize,
}
