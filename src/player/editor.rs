//! The player's instance editor: pick an instance, move it on the horizontal plane through its
//! centre or along the up axis, turn it about the up axis, scale it uniformly, duplicate it,
//! delete it, undo / redo, save. CPU logic over an [`InstancedScene`]; the player puts each
//! [`Change`] on the device (one instance's transform and Δp, or the whole scene after a
//! duplicate or delete).
//!
//! An edit applies a world-space similarity E to one instance: its template → world transform
//! X becomes E∘X and its world-space offsets Δp (added after the transform, paper Eq. 6) become
//! s_E·R_E·Δp, so the instance moves as one body, offsets included. Colour and opacity offsets
//! do not depend on the pose. Coordinates are world units; the up axis is the player's `--up`.
use std::borrow::Cow;
use std::io::Write;
use std::path::{Path, PathBuf};

use anyhow::{bail, Result};
use glam::{Mat3, Quat, Vec3};

use crate::formats::instgs::Storage;
use crate::math::{quat_to_mat, sigmoid};
use crate::model::instanced::{Instance, InstancedScene, Offsets, Similarity};

/// An instance: (group index, instance index within the group).
pub type InstanceRef = (usize, usize);

/// One instance's pose: its transform and its level-0 Δp (T rows).
#[derive(Clone, Debug, PartialEq)]
pub struct Pose {
    pub transform: Similarity,
    pub d_means: Vec<[f32; 3]>,
}

/// What an edit changed, for the device.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Change {
    /// Instance `k` of group `group` moved; `linear` maps its old Δp to the new ones.
    Instance { group: usize, k: usize, linear: Mat3 },
    /// Instances were added or removed: the scene is uploaded again.
    Layout,
}

#[derive(Clone, Debug)]
enum Edit {
    Pose {
        group: usize,
        k: usize,
        before: Pose,
        after: Pose,
        linear: Mat3,
        what: String,
    },
    /// Instance (and its T offset rows) inserted at index `k` (duplicate), or removed from
    /// there (delete).
    Insert {
        group: usize,
        k: usize,
        instance: Instance,
        offsets: Offsets,
    },
    Remove {
        group: usize,
        k: usize,
        instance: Instance,
        offsets: Offsets,
    },
}

/// Editing state: the selection, the undo and redo stacks, where the last save was.
pub struct Editor {
    pub selected: Option<InstanceRef>,
    undo: Vec<Edit>,
    redo: Vec<Edit>,
    /// Undo depth of the saved state; None once that state cannot be reached by undo/redo.
    saved: Option<usize>,
    backed_up: bool,
    /// Per group: the template's means' bounding box (template space).
    boxes: Vec<(Vec3, Vec3)>,
}

/// The similarity p ↦ centre + s·R·(p − centre).
fn about(centre: Vec3, rotation: Quat, scale: f32) -> Similarity {
    Similarity::from_parts(rotation, scale, centre - rotation * (centre * scale))
}

/// `scene` without groups left with no instance (what is uploaded and saved).
pub fn renderable(scene: &InstancedScene) -> Cow<'_, InstancedScene> {
    if scene.groups.iter().all(|g| !g.instances.is_empty()) {
        return Cow::Borrowed(scene);
    }
    let mut s = scene.clone();
    s.groups.retain(|g| !g.instances.is_empty());
    Cow::Owned(s)
}

/// Group `group`'s index on the device (groups without instances are not uploaded).
pub fn device_group(scene: &InstancedScene, group: usize) -> usize {
    scene.groups[..group].iter().filter(|g| !g.instances.is_empty()).count()
}

/// Ray hits of Gaussians: (ray parameter of the peak response, alpha there). The ray is
/// o + t·d in the Gaussians' frame; each Gaussian is (mean, log-scales, quat, opacity logit).
/// The response along the ray peaks where the Mahalanobis distance is smallest (as ray-traced
/// Gaussians are evaluated); alpha there is sigmoid(opacity)·exp(−d²/2). Hits behind the
/// origin and below 1/255 are dropped.
fn ray_hit(mean: Vec3, log_scale: [f32; 3], quat: [f32; 4], opacity: f32, o: Vec3, d: Vec3) -> Option<(f32, f32)> {
    let rt = quat_to_mat(quat).transpose();
    let inv_s = Vec3::from(log_scale.map(|v| (-v).exp()));
    let (lo, ld) = (rt * (o - mean) * inv_s, rt * d * inv_s);
    let dd = ld.length_squared();
    if dd <= 0.0 || !dd.is_finite() {
        return None;
    }
    let t = -lo.dot(ld) / dd;
    let alpha = sigmoid(opacity) * (-0.5 * (lo + ld * t).length_squared()).exp();
    (t > 0.0 && alpha >= 1.0 / 255.0).then_some((t, alpha))
}

impl Editor {
    pub fn new(scene: &InstancedScene) -> Editor {
        let boxes = scene
            .groups
            .iter()
            .map(|g| {
                g.template.means.iter().fold((Vec3::INFINITY, Vec3::NEG_INFINITY), |(lo, hi), m| {
                    (lo.min(Vec3::from(*m)), hi.max(Vec3::from(*m)))
                })
            })
            .collect();
        Editor { selected: None, undo: Vec::new(), redo: Vec::new(), saved: Some(0), backed_up: false, boxes }
    }

    /// Edits since the last save (or since opening).
    pub fn unsaved(&self) -> bool {
        self.saved != Some(self.undo.len())
    }

    /// Edits that undo would revert.
    pub fn edits(&self) -> usize {
        self.undo.len()
    }

    /// The instance's bounding box corners in world space (template means' box, placed).
    pub fn box_corners(&self, scene: &InstancedScene, group: usize, k: usize) -> [Vec3; 8] {
        let (lo, hi) = self.boxes[group];
        let x = &scene.groups[group].instances[k].transform;
        std::array::from_fn(|i| {
            let p = Vec3::new(
                if i & 1 == 0 { lo.x } else { hi.x },
                if i & 2 == 0 { lo.y } else { hi.y },
                if i & 4 == 0 { lo.z } else { hi.z },
            );
            x.rotation * (p * x.scale) + x.translation
        })
    }

    /// The instance's centre in world space: its template's box centre, placed.
    pub fn centre(&self, scene: &InstancedScene, group: usize, k: usize) -> Vec3 {
        let (lo, hi) = self.boxes[group];
        let x = &scene.groups[group].instances[k].transform;
        x.rotation * (0.5 * (lo + hi) * x.scale) + x.translation
    }

    pub fn pose(&self, scene: &InstancedScene, group: usize, k: usize) -> Pose {
        let g = &scene.groups[group];
        let t = g.template.len();
        Pose { transform: g.instances[k].transform, d_means: g.offsets.d_means[k * t..(k + 1) * t].to_vec() }
    }

    fn set_pose(scene: &mut InstancedScene, group: usize, k: usize, pose: &Pose) {
        let g = &mut scene.groups[group];
        let t = g.template.len();
        g.instances[k].transform = pose.transform;
        g.offsets.d_means[k * t..(k + 1) * t].copy_from_slice(&pose.d_means);
    }

    /// `pose` moved by the world similarity `e`.
    fn moved(pose: &Pose, e: &Similarity) -> (Pose, Mat3) {
        let linear = Mat3::from_quat(e.rotation) * e.scale;
        let d_means = pose.d_means.iter().map(|d| (linear * Vec3::from(*d)).to_array()).collect();
        (Pose { transform: e.compose(&pose.transform), d_means }, linear)
    }

    fn push(&mut self, edit: Edit) {
        if self.saved.is_some_and(|s| s > self.undo.len()) {
            self.saved = None;
        }
        self.undo.push(edit);
        self.redo.clear();
    }

    /// Applies `e` to the selected instance as one undoable edit described by `what`.
    fn transform(&mut self, scene: &mut InstancedScene, e: &Similarity, what: String) -> Option<(Change, String)> {
        let (group, k) = self.selected?;
        let before = self.pose(scene, group, k);
        let (after, linear) = Self::moved(&before, e);
        Self::set_pose(scene, group, k, &after);
        let what = format!("{what} instance {}", scene.groups[group].instances[k].id);
        self.push(Edit::Pose { group, k, before, after, linear, what: what.clone() });
        Some((Change::Instance { group, k, linear }, what))
    }

    /// Turns the selection by `degrees` about the up axis through its centre.
    pub fn turn(&mut self, scene: &mut InstancedScene, degrees: f32, up: Vec3) -> Option<(Change, String)> {
        let (group, k) = self.selected?;
        let c = self.centre(scene, group, k);
        let e = about(c, Quat::from_axis_angle(up.normalize(), degrees.to_radians()), 1.0);
        self.transform(scene, &e, format!("turned by {degrees}° about the up axis:"))
    }

    /// Scales the selection by `factor` about its centre.
    pub fn scale(&mut self, scene: &mut InstancedScene, factor: f32) -> Option<(Change, String)> {
        let (group, k) = self.selected?;
        let c = self.centre(scene, group, k);
        self.transform(scene, &about(c, Quat::IDENTITY, factor), format!("scaled by {factor}:"))
    }

    /// While dragging: the selection at `start` moved by `delta` (world units); no undo entry
    /// until [`Editor::commit_move`].
    pub fn preview_move(&mut self, scene: &mut InstancedScene, start: &Pose, delta: Vec3) -> Option<Change> {
        let (group, k) = self.selected?;
        let e = Similarity::from_parts(Quat::IDENTITY, 1.0, delta);
        Self::set_pose(
            scene,
            group,
            k,
            &Pose { transform: e.compose(&start.transform), d_means: start.d_means.clone() },
        );
        Some(Change::Instance { group, k, linear: Mat3::IDENTITY })
    }

    /// Ends a drag that began at `start`: one undoable edit (none if nothing moved).
    pub fn commit_move(&mut self, scene: &InstancedScene, start: Pose) -> Option<String> {
        let (group, k) = self.selected?;
        let after = self.pose(scene, group, k);
        if after == start {
            return None;
        }
        let d = after.transform.translation - start.transform.translation;
        let what =
            format!("moved instance {} by ({:.4}, {:.4}, {:.4})", scene.groups[group].instances[k].id, d.x, d.y, d.z);
        self.push(Edit::Pose { group, k, before: start, after, linear: Mat3::IDENTITY, what: what.clone() });
        Some(what)
    }

    /// A new instance of the selection's template, zero offsets, moved by `shift`; selected.
    pub fn duplicate(&mut self, scene: &mut InstancedScene, shift: Vec3) -> Option<(Change, String)> {
        let (group, k) = self.selected?;
        let taken = |id: &str| scene.groups.iter().flat_map(|g| &g.instances).any(|i| i.id == id);
        let base = &scene.groups[group].instances[k];
        let id = (1..).map(|n| format!("{}-copy{}", base.id, if n == 1 { String::new() } else { n.to_string() }));
        let id = id.into_iter().find(|id| !taken(id)).expect("unbounded");
        let e = Similarity::from_parts(Quat::IDENTITY, 1.0, shift);
        let instance = Instance { id, transform: e.compose(&base.transform) };
        let what = format!("duplicated instance {} as {}", base.id, instance.id);
        let offsets = Offsets::zeros(scene.groups[group].template.len());
        Self::insert(scene, group, k + 1, &instance, &offsets);
        self.push(Edit::Insert { group, k: k + 1, instance, offsets });
        self.selected = Some((group, k + 1));
        Some((Change::Layout, what))
    }

    /// Deletes the selection (refused where the scene would have no Gaussian left).
    pub fn delete(&mut self, scene: &mut InstancedScene) -> Result<Option<(Change, String)>> {
        let Some((group, k)) = self.selected else { return Ok(None) };
        if scene.splats() == scene.groups[group].template.len() {
            bail!("not deleted: instance {} holds the scene's last Gaussians", scene.groups[group].instances[k].id);
        }
        let (instance, offsets) = Self::remove(scene, group, k);
        let what = format!("deleted instance {}", instance.id);
        self.push(Edit::Remove { group, k, instance, offsets });
        self.selected = None;
        Ok(Some((Change::Layout, what)))
    }

    fn insert(scene: &mut InstancedScene, group: usize, k: usize, instance: &Instance, offsets: &Offsets) {
        let g = &mut scene.groups[group];
        let at = k * g.template.len();
        g.instances.insert(k, instance.clone());
        let o = &mut g.offsets;
        o.d_means.splice(at..at, offsets.d_means.iter().copied());
        o.d_sh0.splice(at..at, offsets.d_sh0.iter().copied());
        o.d_opacities.splice(at..at, offsets.d_opacities.iter().copied());
    }

    fn remove(scene: &mut InstancedScene, group: usize, k: usize) -> (Instance, Offsets) {
        let g = &mut scene.groups[group];
        let t = g.template.len();
        let r = k * t..(k + 1) * t;
        let o = &mut g.offsets;
        let offsets = Offsets {
            d_means: o.d_means.drain(r.clone()).collect(),
            d_sh0: o.d_sh0.drain(r.clone()).collect(),
            d_opacities: o.d_opacities.drain(r).collect(),
        };
        (g.instances.remove(k), offsets)
    }

    /// Applies `edit` forwards (redo) or backwards (undo); the selection follows the instance.
    fn apply(&mut self, scene: &mut InstancedScene, edit: &Edit, forwards: bool) -> (Change, String) {
        let verb = if forwards { "redo" } else { "undo" };
        match edit {
            Edit::Pose { group, k, before, after, linear, what } => {
                Self::set_pose(scene, *group, *k, if forwards { after } else { before });
                self.selected = Some((*group, *k));
                let linear = if forwards { *linear } else { linear.inverse() };
                (Change::Instance { group: *group, k: *k, linear }, format!("{verb}: {what}"))
            }
            Edit::Insert { group, k, instance, offsets } | Edit::Remove { group, k, instance, offsets } => {
                let inserting = matches!(edit, Edit::Insert { .. }) == forwards;
                if inserting {
                    Self::insert(scene, *group, *k, instance, offsets);
                    self.selected = Some((*group, *k));
                } else {
                    Self::remove(scene, *group, *k);
                    self.selected = None;
                }
                let did = if inserting { "instance back" } else { "instance removed" };
                (Change::Layout, format!("{verb}: {did}: {}", instance.id))
            }
        }
    }

    pub fn undo(&mut self, scene: &mut InstancedScene) -> Option<(Change, String)> {
        let edit = self.undo.pop()?;
        let r = self.apply(scene, &edit, false);
        self.redo.push(edit);
        Some(r)
    }

    pub fn redo(&mut self, scene: &mut InstancedScene) -> Option<(Change, String)> {
        let edit = self.redo.pop()?;
        let r = self.apply(scene, &edit, true);
        self.undo.push(edit);
        Some(r)
    }

    /// The instance seen along the ray `origin + t·dir` (world space): Gaussians hit by the ray
    /// (background and every instance's, offsets applied) are composited front to back and the
    /// owner of the one where the transmittance falls below one half wins; None where that is
    /// a background Gaussian or the ray stays mostly clear.
    pub fn pick(&self, scene: &InstancedScene, origin: Vec3, dir: Vec3) -> Option<InstanceRef> {
        // (ray parameter, alpha, owner: None for the background)
        let mut hits: Vec<(f32, f32, Option<InstanceRef>)> = Vec::new();
        let bg = &scene.background;
        for i in 0..bg.len() {
            if let Some((t, a)) = ray_hit(bg.means[i].into(), bg.scales[i], bg.quats[i], bg.opacities[i], origin, dir) {
                hits.push((t, a, None));
            }
        }
        for (gi, g) in scene.groups.iter().enumerate() {
            let (lo, hi) = self.boxes[gi];
            let t = &g.template;
            // 3σ of the template's largest Gaussian (template space).
            let reach = 3.0 * t.scales.iter().flatten().fold(f32::NEG_INFINITY, |m, &v| m.max(v)).exp();
            for (k, inst) in g.instances.iter().enumerate() {
                let x = &inst.transform;
                let inv = x.rotation.inverse();
                // The ray in template space (same parameter t: the map is affine).
                let (o, d) = (inv * (origin - x.translation) / x.scale, inv * dir / x.scale);
                let d_means = &g.offsets.d_means[k * t.len()..(k + 1) * t.len()];
                // Skip instances whose box (grown by their Gaussians and offsets) the ray misses.
                let grow = d_means.iter().map(|v| Vec3::from(*v).length()).fold(0.0f32, f32::max) / x.scale + reach;
                let (blo, bhi) = (lo - Vec3::splat(grow), hi + Vec3::splat(grow));
                let (ta, tb) = ((blo - o) / d, (bhi - o) / d);
                let (near, far) = (ta.min(tb).max_element(), ta.max(tb).min_element());
                if !(near <= far && far > 0.0) {
                    continue;
                }
                for (j, dp) in d_means.iter().enumerate() {
                    let mean = Vec3::from(t.means[j]) + inv * Vec3::from(*dp) / x.scale;
                    let opacity = t.opacities[j] + g.offsets.d_opacities[k * t.len() + j];
                    if let Some((s, a)) = ray_hit(mean, t.scales[j], t.quats[j], opacity, o, d) {
                        hits.push((s, a, Some((gi, k))));
                    }
                }
            }
        }
        hits.sort_by(|a, b| a.0.total_cmp(&b.0));
        let mut transmittance = 1.0f32;
        for (_, a, owner) in hits {
            transmittance *= 1.0 - a;
            if transmittance < 0.5 {
                return owner;
            }
        }
        None
    }

    /// Writes the scene to `path` (atomically; `.glb`/`.gltf` as an instanced glTF, else
    /// `.instgs` with offsets stored as `dtype`; groups without instances left out); the first save of a session first keeps the file as it was as
    /// `PATH.bak`. Returns the backup's path when one was made.
    pub fn save(&mut self, scene: &InstancedScene, path: &Path, storage: Storage) -> Result<Option<PathBuf>> {
        let scene = renderable(scene);
        scene.validate(&path.display().to_string())?;
        let mut backup = None;
        if !self.backed_up && path.exists() {
            let bak = PathBuf::from(format!("{}.bak", path.display()));
            let original = std::fs::read(path).map_err(|e| anyhow::anyhow!("{}: cannot read: {e}", path.display()))?;
            crate::util::write_atomic(&bak, |f| f.write_all(&original))?;
            backup = Some(bak);
        }
        // A glTF scene stays glTF (its templates shared); anything else is written as .instgs.
        let name = path.to_string_lossy().to_ascii_lowercase();
        if name.ends_with(".glb") || name.ends_with(".gltf") {
            crate::formats::gltf::write_instanced_gltf(&scene, path, crate::formats::gltf::Accessors::Float)?;
        } else {
            crate::formats::instgs::write_stored(&scene, path, storage)?;
        }
        self.backed_up = true;
        self.saved = Some(self.undo.len());
        Ok(backup)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::instanced::Group;
    use crate::model::scene::Scene;

    /// A template of `n` small opaque Gaussians on a 0.2-wide grid around the origin.
    fn template(n: usize) -> Scene {
        let mut t = Scene { sh_degree: 0, ..Default::default() };
        for i in 0..n {
            let f = i as f32 / n as f32;
            t.means.push([0.2 * f - 0.1, 0.1 * (7.0 * f).sin(), 0.1 * (3.0 * f).cos()]);
            t.scales.push([-3.0, -3.5, -3.2]);
            t.quats.push([1.0, 0.1 * f, 0.0, 0.2]);
            t.opacities.push(3.0);
            t.sh.extend([0.5, 0.2, 0.1]);
        }
        t
    }

    /// Two instances of one template along x (at x = 0 and x = 1), random Δp, and one
    /// background Gaussian at `background`.
    fn scene(background: Vec3) -> InstancedScene {
        let t = template(40);
        let mut offsets = Offsets::zeros(2 * t.len());
        for (i, d) in offsets.d_means.iter_mut().enumerate() {
            *d = [0.01 * (i as f32).sin(), 0.01 * (i as f32).cos(), 0.004];
        }
        let instances = [(0.0, "a"), (1.0, "b")]
            .map(|(x, id)| Instance {
                id: id.into(),
                transform: Similarity::from_parts(Quat::from_rotation_z(0.3), 1.2, Vec3::new(x, 0.0, 0.0)),
            })
            .to_vec();
        let mut bg = template(1);
        bg.means[0] = background.to_array();
        bg.scales[0] = [-1.0; 3];
        InstancedScene {
            sh_degree: 0,
            background: bg,
            groups: vec![Group { name: "g".into(), template: t, instances, offsets }],
        }
    }

    fn expanded(scene: &InstancedScene, k: usize) -> Vec<Vec3> {
        let t = scene.groups[0].template.len();
        scene.expanded_means()[1 + k * t..1 + (k + 1) * t].iter().map(|m| Vec3::from(*m)).collect()
    }

    #[test]
    fn turns_and_scales_move_the_instance_as_one_body_and_undo_restores_it() {
        let mut s = scene(Vec3::new(0.0, 0.0, -50.0));
        let original = s.clone();
        let mut ed = Editor::new(&s);
        assert!(ed.turn(&mut s, 15.0, Vec3::Z).is_none(), "nothing selected");
        ed.selected = Some((0, 1));
        let c = ed.centre(&s, 0, 1);
        let before = expanded(&s, 1);
        let (change, what) = ed.turn(&mut s, 90.0, Vec3::Z).unwrap();
        assert!(what.contains("instance b"), "{what}");
        let Change::Instance { group: 0, k: 1, linear } = change else { panic!("{change:?}") };
        assert!((linear - Mat3::from_rotation_z(90f32.to_radians())).abs_diff_eq(Mat3::ZERO, 1e-6));
        // Every expanded mean (offsets included) turned about the vertical through the centre.
        let r = Quat::from_rotation_z(90f32.to_radians());
        for (a, b) in before.iter().zip(expanded(&s, 1)) {
            assert!((c + r * (*a - c) - b).length() < 1e-5);
        }
        assert_eq!(expanded(&s, 0), expanded(&original, 0), "the other instance stays");
        ed.scale(&mut s, 2.0).unwrap();
        let turned = expanded(&s, 1);
        assert!((ed.centre(&s, 0, 1) - c).length() < 1e-5, "scaling keeps the centre");
        assert!(ed.unsaved() && ed.edits() == 2);
        ed.undo(&mut s).unwrap();
        ed.undo(&mut s).unwrap();
        assert_eq!(s, original, "undo restores the file's values exactly");
        assert!(!ed.unsaved());
        assert!(ed.undo(&mut s).is_none());
        ed.redo(&mut s).unwrap();
        ed.redo(&mut s).unwrap();
        for (a, b) in turned.iter().zip(expanded(&s, 1)) {
            assert!((*a - b).length() < 1e-6);
        }
    }

    #[test]
    fn duplicate_and_delete_keep_the_offsets_aligned_and_undo() {
        let mut s = scene(Vec3::new(0.0, 0.0, -50.0));
        let original = s.clone();
        let mut ed = Editor::new(&s);
        ed.selected = Some((0, 0));
        let (change, what) = ed.duplicate(&mut s, Vec3::new(0.0, 2.0, 0.0)).unwrap();
        assert_eq!(change, Change::Layout);
        assert_eq!(what, "duplicated instance a as a-copy");
        assert_eq!(ed.selected, Some((0, 1)));
        let g = &s.groups[0];
        let t = g.template.len();
        assert_eq!(g.instances.iter().map(|i| i.id.as_str()).collect::<Vec<_>>(), ["a", "a-copy", "b"]);
        assert!(g.offsets.d_means[t..2 * t].iter().all(|d| *d == [0.0; 3]), "zero offsets");
        assert_eq!(g.offsets.d_means[2 * t..], original.groups[0].offsets.d_means[t..], "b keeps its offsets");
        let x = g.instances[1].transform;
        assert_eq!(x.translation, original.groups[0].instances[0].transform.translation + Vec3::new(0.0, 2.0, 0.0));
        s.validate("duplicated").unwrap();
        ed.selected = Some((0, 0));
        ed.duplicate(&mut s, Vec3::X).unwrap();
        assert_eq!(s.groups[0].instances[1].id, "a-copy2");
        // Delete b, then undo everything.
        ed.selected = Some((0, 3));
        assert_eq!(ed.delete(&mut s).unwrap().unwrap().1, "deleted instance b");
        assert_eq!(s.groups[0].instances.len(), 3);
        s.validate("deleted").unwrap();
        while ed.undo(&mut s).is_some() {}
        assert_eq!(s, original);
        // The last instances go, the group is left out of what is rendered; the last
        // Gaussians of a scene are not deleted.
        let mut s = scene(Vec3::ZERO);
        s.background = Scene { sh_degree: 0, ..Default::default() };
        let mut ed = Editor::new(&s);
        ed.selected = Some((0, 0));
        ed.delete(&mut s).unwrap();
        ed.selected = Some((0, 0));
        let e = ed.delete(&mut s).unwrap_err().to_string();
        assert!(e.contains("last Gaussians"), "{e}");
        let mut two = scene(Vec3::ZERO);
        two.groups.push(two.groups[0].clone());
        let mut ed = Editor::new(&two);
        for _ in 0..2 {
            ed.selected = Some((0, 0));
            ed.delete(&mut two).unwrap();
        }
        assert_eq!(renderable(&two).groups.len(), 1);
        assert_eq!(device_group(&two, 1), 0);
    }

    #[test]
    fn a_ray_picks_the_front_instance_and_the_background_hides() {
        // Instances at x = 0 and x = 1 (each ~0.24 wide), a ray along −x from x = 5.
        let s = scene(Vec3::new(0.0, 0.0, -50.0));
        let ed = Editor::new(&s);
        let (c0, c1) = (ed.centre(&s, 0, 0), ed.centre(&s, 0, 1));
        assert_eq!(ed.pick(&s, c1 + Vec3::new(5.0, 0.0, 0.0), -Vec3::X), Some((0, 1)), "b is in front");
        assert_eq!(ed.pick(&s, c0 - Vec3::new(5.0, 0.0, 0.0), Vec3::X), Some((0, 0)), "from the other side: a");
        assert_eq!(ed.pick(&s, c1 + Vec3::new(5.0, 0.0, 0.0), Vec3::X), None, "behind the eye");
        assert_eq!(ed.pick(&s, c1 + Vec3::new(0.0, 5.0, 0.0), -Vec3::Y), Some((0, 1)));
        assert_eq!(ed.pick(&s, c1 + Vec3::new(0.0, 5.0, 3.0), -Vec3::Y), None, "a miss");
        // An opaque background Gaussian in front of b.
        let s = scene(c1 + Vec3::new(2.0, 0.0, 0.0));
        assert_eq!(ed.pick(&s, c1 + Vec3::new(5.0, 0.0, 0.0), -Vec3::X), None);
    }

    #[test]
    fn save_writes_the_edits_and_keeps_the_original_once() {
        let dir = std::env::temp_dir().join(format!("instgs-editor-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("s.instgs");
        let mut s = scene(Vec3::new(0.0, 0.0, -50.0));
        crate::formats::instgs::write(&s, &path, crate::formats::instgs::Dtype::F32).unwrap();
        let original = std::fs::read(&path).unwrap();
        let mut ed = Editor::new(&s);
        ed.selected = Some((0, 0));
        ed.turn(&mut s, 30.0, Vec3::Z).unwrap();
        let bak = ed.save(&s, &path, Storage::F32).unwrap().unwrap();
        assert_eq!(bak, dir.join("s.instgs.bak"));
        assert_eq!(std::fs::read(&bak).unwrap(), original);
        assert!(!ed.unsaved());
        assert_eq!(crate::formats::instgs::read(&path).unwrap(), s);
        ed.scale(&mut s, 1.05).unwrap();
        assert!(ed.save(&s, &path, Storage::F32).unwrap().is_none(), "one backup per session");
        assert_eq!(std::fs::read(&bak).unwrap(), original);
        assert_eq!(crate::formats::instgs::read(&path).unwrap(), s);
        ed.undo(&mut s).unwrap();
        assert!(ed.unsaved());
        // A compressed file is saved compressed again.
        let small = dir.join("small.instgs");
        crate::formats::instgs::write_compressed(&s, &small).unwrap();
        let (mut c, storage) = crate::formats::instgs::read_with_storage(&small).unwrap();
        assert_eq!(storage, Storage::COMPRESSED);
        let mut ed = Editor::new(&c);
        ed.selected = Some((0, 0));
        ed.turn(&mut c, 10.0, Vec3::Z).unwrap();
        ed.save(&c, &small, storage).unwrap();
        let (back, again) = crate::formats::instgs::read_with_storage(&small).unwrap();
        assert_eq!(again, Storage::COMPRESSED);
        assert_eq!(back.groups[0].instances, c.groups[0].instances);
        // An instanced glTF opened in the player is saved as glTF again.
        let glb = dir.join("s.glb");
        crate::formats::gltf::write_instanced_gltf(&s, &glb, crate::formats::gltf::Accessors::Float).unwrap();
        let mut ed = Editor::new(&s);
        ed.selected = Some((0, 0));
        ed.turn(&mut s, 20.0, Vec3::Z).unwrap();
        ed.save(&s, &glb, Storage::F32).unwrap();
        let crate::formats::AnyScene::Instanced(back) = crate::formats::AnyScene::read(&glb).unwrap() else {
            panic!("the saved .glb reads as a plain scene")
        };
        let (a, b) = (back.groups[0].instances[0].transform, s.groups[0].instances[0].transform);
        assert!(a.rotation.dot(b.rotation).abs() > 1.0 - 1e-6 && a.translation.distance(b.translation) < 1e-4);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn camera_rays_go_through_projected_points() {
        let cam = crate::model::camera::orbit_around_points(
            &[[0.0; 3], [1.0, 1.0, 1.0]],
            1,
            crate::model::camera::UpAxis::PosZ,
            64,
            48,
        )
        .remove(0);
        let p = Vec3::new(0.3, 0.6, 0.2);
        let [u, v, depth] = cam.project(p).unwrap();
        let (o, d) = cam.ray(u, v);
        let along = (p - o).dot(d);
        assert!((o + d * along - p).length() < 1e-4 && along > 0.0 && depth > 0.0);
        assert!(cam.project(o - d).is_none(), "behind the camera");
    }
}
