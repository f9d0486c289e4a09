//! Repetition found in 3D (`instgs-vk discover`): instances of a plain scene found without
//! per-instance masks, from one example or from none.
//!
//! * **From an example** ([`from_example`]): the example's Gaussians (a 3D box, a label of a
//!   labels file, or one view's mask lifted into the scene, [`run`]) are matched against the
//!   rest of the scene: FPFH features on voxel-downsampled opaque means (the registration's,
//!   [`crate::register`]), each example point paired with its nearest scene features, and
//!   RANSAC over 3-point samples drawn within one example size of each other, scored by the
//!   example points that land on their paired scene points. The best placement is refined by ICP
//!   onto the scene points around it; the Gaussians within reach of the placed example are the
//!   candidate copy, which is then registered and checked like any instance
//!   ([`register_and_check`]: two-sided fitness, scale against the clouds' size ratio, the render
//!   check against the training views). An accepted copy's Gaussians leave the search and the
//!   next round looks for another; the search ends when a round's best placements are all
//!   refused.
//! * **From none** ([`auto`]): the dominant plane of the opaque means (RANSAC, then least
//!   squares) is taken as the support; what stands on it is split into connected clusters
//!   (links of a few point spacings), each with its bottom (the plane's slab inside its
//!   footprint, [`Support::object_gaussians`]); clusters are grouped by registering each onto the
//!   references of the groups found so far (largest first; onto up to three members of a
//!   group, the first first) with the same checks; each group's
//!   reference (of groups with two members or more) then searches the rest of the scene as an
//!   example does, for copies the clusters merged or missed. Groups with one member, and clusters that fit nothing, stay background.
//!
//! Poses are reported as in the instance stage: instance world → reference world.
mod copies;
pub mod run;
mod support;

pub use copies::from_example;
pub use support::{find_support, Support};

use std::collections::HashMap;

use anyhow::Result;
use kiddo::SquaredEuclidean;

use crate::instancing::options::{InstanceOptions, Status};
use crate::instancing::pose::InstanceReport;
use crate::instancing::pose::{register_and_check, RenderCheck};
use crate::math::tree;
use crate::model::scene::Scene;
use crate::register::{centroid, median_spacing, object_size, Sim3};

use copies::{f64s, object_cloud, opaque, search_copies};

/// Settings of the search (configuration `[discover]`, configs/pipeline.toml).
#[derive(Clone, Debug)]
pub struct DiscoverOptions {
    /// Registration and acceptance, as in the instance stage.
    pub instance: InstanceOptions,
    /// RANSAC samples per search round.
    pub ransac_iterations: usize,
    /// Placements checked per round, the best first; a round whose placements are all refused
    /// ends the search.
    pub placements_per_round: usize,
    /// A placement counts when at least this fraction of the example's points land on a scene
    /// point (and 2 % of them on their paired ones).
    pub min_inlier_fraction: f64,
    /// Gaussians within this many registration voxels of a placed example Gaussian make up the
    /// candidate copy.
    pub claim_voxels: f64,
    /// Support plane (auto): its thickness in median spacings of the opaque Gaussians (a
    /// trained surface is a thin sheet of them).
    pub plane_spacings: f64,
    /// Clusters (auto): at least this many opaque Gaussians.
    pub min_cluster: usize,
    /// Clusters (auto): at most this fraction of the scene's size.
    pub max_cluster_size: f64,
    /// Copies per group at most.
    pub max_copies: usize,
    /// Groups (auto) whose objects are smaller than this fraction of the largest group's
    /// objects are specks, not objects: dropped and reported (BENCHMARKS.md says how it was
    /// chosen).
    pub min_object_fraction: f64,
}

impl Default for DiscoverOptions {
    fn default() -> Self {
        DiscoverOptions {
            instance: InstanceOptions::default(),
            ransac_iterations: 20_000,
            placements_per_round: 2,
            min_inlier_fraction: 0.5,
            claim_voxels: 1.5,
            plane_spacings: 2.5,
            min_cluster: 30,
            max_cluster_size: 0.4,
            max_copies: 64,
            min_object_fraction: 0.25,
        }
    }
}

/// One instance found: its Gaussians (scene indices) and its pose onto the group's reference.
#[derive(Clone, Debug)]
pub struct Member {
    pub id: u32,
    pub gaussians: Vec<usize>,
    /// Instance world → reference world (identity for the reference).
    pub relative: Sim3,
    /// The checks of that pose (None for the reference).
    pub report: Option<InstanceReport>,
}

/// A group: its reference (the example, or the largest cluster) first.
#[derive(Clone, Debug)]
pub struct FoundGroup {
    pub name: String,
    pub members: Vec<Member>,
}

/// What a search found and what it refused.
#[derive(Clone, Debug, Default)]
pub struct Discovery {
    pub groups: Vec<FoundGroup>,
    /// One line per refused candidate: where, and why.
    pub refused: Vec<String>,
}

impl Discovery {
    /// Per-Gaussian labels (0 = background) of the groups with at least two members.
    pub fn labels(&self, n: usize) -> Vec<u32> {
        let mut labels = vec![0; n];
        for g in self.groups.iter().filter(|g| g.members.len() > 1) {
            for m in &g.members {
                for &i in &m.gaussians {
                    labels[i] = m.id;
                }
            }
        }
        labels
    }
}

/// Connected components of `points` linked within `link` (union–find over a k-d tree's radius
/// queries), largest first; each a list of indices.
pub fn clusters(points: &[[f64; 3]], link: f64) -> Vec<Vec<usize>> {
    fn root(p: &mut [usize], mut i: usize) -> usize {
        while p[i] != i {
            p[i] = p[p[i]];
            i = p[i];
        }
        i
    }
    if points.is_empty() {
        return Vec::new();
    }
    let t = tree(points);
    let mut parent: Vec<usize> = (0..points.len()).collect();
    for (i, p) in points.iter().enumerate() {
        for nb in t.within_unsorted::<SquaredEuclidean>(p, link * link) {
            let (a, b) = (root(&mut parent, i), root(&mut parent, nb.item as usize));
            if a != b {
                parent[a.max(b)] = a.min(b);
            }
        }
    }
    let mut by_root: HashMap<usize, Vec<usize>> = HashMap::new();
    for i in 0..points.len() {
        let r = root(&mut parent, i);
        by_root.entry(r).or_default().push(i);
    }
    let mut out: Vec<Vec<usize>> = by_root.into_values().collect();
    out.sort_by_key(|c| (std::cmp::Reverse(c.len()), c[0]));
    out
}

/// The objects standing on the support plane, each as its scene Gaussians (sorted): clusters of
/// the opaque Gaussians above the slab (`op`, their means `pts`) linked within three median
/// spacings, of at least `o.min_cluster` points and at most `o.max_cluster_size` × the scene's
/// size; every Gaussian above the slab within one link of a cluster's points belongs to it, and
/// so do the slab's Gaussians inside its footprint (its bottom).
#[allow(clippy::too_many_arguments)]
fn object_candidates(
    scene: &Scene,
    support: &Support,
    op: &[usize],
    pts: &[[f64; 3]],
    scene_size: f64,
    o: &DiscoverOptions,
    io: &InstanceOptions,
    progress: &mut impl FnMut(&str),
) -> Vec<Vec<usize>> {
    let thickness = support.thickness;
    let standing: Vec<usize> =
        (0..pts.len()).filter(|&k| support.height(scene.means[op[k]]) > 1.5 * thickness).collect();
    let standing_pts: Vec<[f64; 3]> = standing.iter().map(|&k| pts[k]).collect();
    let link = (3.0 * median_spacing(&standing_pts)).max(0.5 * thickness);
    let found: Vec<Vec<usize>> = clusters(&standing_pts, link)
        .into_iter()
        .filter(|c| c.len() >= o.min_cluster)
        .filter(|c| {
            let cp: Vec<[f64; 3]> = c.iter().map(|&k| standing_pts[k]).collect();
            object_size(&cp) <= o.max_cluster_size * scene_size
        })
        .collect();
    progress(&format!("{} object candidates stand on it (links of {:.4})", found.len(), link));
    let mut owner = vec![usize::MAX; standing_pts.len()];
    for (c, members) in found.iter().enumerate() {
        for &k in members {
            owner[k] = c;
        }
    }
    let t = tree(&standing_pts);
    let mut gaussians: Vec<Vec<usize>> = vec![Vec::new(); found.len()];
    for i in 0..scene.len() {
        let nn = t.nearest_one::<SquaredEuclidean>(&f64s(scene.means[i]));
        let c = owner[nn.item as usize];
        if c != usize::MAX && nn.distance <= link * link && support.height(scene.means[i]) > 1.5 * thickness {
            gaussians[c].push(i);
        }
    }
    let hulls: Vec<Option<Vec<[f64; 2]>>> =
        gaussians.iter().map(|g| support.footprint(scene, g, io.min_opacity)).collect();
    for i in (0..scene.len()).filter(|&i| support.in_slab(scene.means[i])) {
        if let Some(c) = hulls.iter().position(|h| h.as_ref().is_some_and(|h| support.fits_inside(h, scene, i))) {
            gaussians[c].push(i);
        }
    }
    for g in gaussians.iter_mut() {
        g.sort_unstable();
    }
    gaussians
}

/// Finds groups of repeated objects with no example ([`auto`] in the module docs).
pub fn auto(
    scene: &Scene,
    o: &DiscoverOptions,
    mut render_check: Option<&mut dyn RenderCheck>,
    mut progress: impl FnMut(&str),
) -> Result<Discovery> {
    let io = &o.instance;
    let op: Vec<usize> = (0..scene.len()).filter(|&i| opaque(scene, i, io.min_opacity)).collect();
    let pts: Vec<[f64; 3]> = op.iter().map(|&i| f64s(scene.means[i])).collect();
    let scene_size = object_size(&pts);
    if pts.len() < 3 || scene_size <= 0.0 {
        anyhow::bail!("the scene has too few opaque Gaussians ({}) to search", pts.len());
    }
    let support = find_support(scene, o, &mut progress)?;
    let io = &InstanceOptions { up: io.up.or(Some(support.normal)), ..io.clone() };
    let gaussians = object_candidates(scene, &support, &op, &pts, scene_size, o, io, &mut progress);
    // Grouping: each candidate (largest first) onto the references of the groups so far.
    let mut out = Discovery::default();
    let mut next_id = 1u32;
    let mut groups: Vec<FoundGroup> = Vec::new();
    for members in gaussians {
        let part = scene.select(&members);
        let (c_pts, c_rgb) = object_cloud(&part, Some(&support), io.min_opacity);
        let c_size = object_size(&c_pts);
        let id = next_id;
        next_id += 1;
        let centre = centroid(&c_pts);
        let where_ = format!("[{:.3}, {:.3}, {:.3}]", centre[0], centre[1], centre[2]);
        let mut joined = false;
        'groups: for g in groups.iter_mut() {
            // The group's first member, then up to two more: members of one group differ by a
            // tint, and a candidate's colours may match one member's better than the first's.
            let mut last_refusal = None;
            for m in 0..g.members.len().min(3) {
                let r = &g.members[m];
                let r_scene = scene.select(&r.gaussians);
                let (r_pts, r_rgb) = object_cloud(&r_scene, Some(&support), io.min_opacity);
                // Candidates of another size or density are not tried (ratios past 1.5 and 3).
                let ratio = c_size / object_size(&r_pts);
                let count = c_pts.len() as f64 / r_pts.len() as f64;
                if !(1.0 / 1.5..=1.5).contains(&ratio) || !(1.0 / 3.0..=3.0).contains(&count) {
                    continue;
                }
                let reg = io.register_options(object_size(&r_pts));
                let mut report = InstanceReport::new(&g.name, id, r.id, members.len());
                let (pose, status) = register_and_check(
                    &[r_scene, part.clone()],
                    &[r_pts, c_pts.clone()],
                    &[r_rgb, c_rgb.clone()],
                    1,
                    0,
                    &reg,
                    io,
                    &mut render_check,
                    &mut report,
                    &g.name,
                    &[r.id, id],
                )?;
                if status == Status::Accepted {
                    progress(&format!(
                        "candidate {id} at {where_} ({} Gaussians) joins {} onto {} (fitness {:.2} / {:.2}{})",
                        members.len(),
                        g.name,
                        r.id,
                        report.check.fitness,
                        report.check.fitness_reverse,
                        report
                            .render
                            .map(|s| format!(", render IoU {:.2} PSNR {:.1} dB", s.iou, s.psnr))
                            .unwrap_or_default()
                    ));
                    // Onto the group's first: through the member it was registered onto.
                    report.relative = r.relative.compose(&pose);
                    report.reference = g.members[0].id;
                    report.status = status;
                    let relative = report.relative;
                    g.members.push(Member { id, gaussians: members.clone(), relative, report: Some(report) });
                    joined = true;
                    break 'groups;
                }
                last_refusal = Some(format!(
                    "candidate {id} at {where_} onto {} of {}: {}",
                    r.id,
                    g.name,
                    status.reason().unwrap_or("refused")
                ));
            }
            out.refused.extend(last_refusal);
        }
        if !joined {
            let name = format!("group{}", groups.len() + 1);
            progress(&format!("candidate {id} at {where_} ({} Gaussians) starts {name}", members.len()));
            groups.push(FoundGroup {
                name,
                members: vec![Member { id, gaussians: members, relative: Sim3::identity(), report: None }],
            });
        }
    }
    // Copies the clusters merged or missed: each group's reference searches the rest.
    let mut available = vec![true; scene.len()];
    for g in &groups {
        for m in &g.members {
            for &i in &m.gaussians {
                available[i] = false;
            }
        }
    }
    for g in groups.iter_mut().filter(|g| g.members.len() > 1) {
        let reference = g.members[0].clone();
        let more = search_copies(
            scene,
            &reference,
            Some(&support),
            &g.name,
            &mut available,
            o,
            &mut render_check,
            &mut next_id,
            &mut out.refused,
            &mut progress,
        )?;
        g.members.extend(more);
    }
    for g in &groups {
        if g.members.len() == 1 {
            progress(&format!("{}: one member ({}), stays background", g.name, g.members[0].id));
        }
    }
    drop_specks(scene, &support, &mut groups, o, &mut out.refused, &mut progress);
    out.groups = groups;
    Ok(out)
}

/// A repetition worth instancing is an object, not a speck: groups of two or more members whose
/// reference is smaller ([`object_size`] of its opaque cloud) than `o.min_object_fraction` × the
/// largest such group's are dropped (their members stay background), with a line in `refused`.
fn drop_specks(
    scene: &Scene,
    support: &Support,
    groups: &mut Vec<FoundGroup>,
    o: &DiscoverOptions,
    refused: &mut Vec<String>,
    progress: &mut impl FnMut(&str),
) {
    let size = |g: &FoundGroup| {
        object_size(&object_cloud(&scene.select(&g.members[0].gaussians), Some(support), o.instance.min_opacity).0)
    };
    let sizes: Vec<f64> = groups.iter().map(size).collect();
    let largest = groups.iter().zip(&sizes).filter(|(g, _)| g.members.len() > 1).map(|(_, &s)| s).fold(0.0, f64::max);
    let floor = o.min_object_fraction * largest;
    let mut k = 0;
    groups.retain(|g| {
        let s = sizes[k];
        k += 1;
        if g.members.len() < 2 || s >= floor {
            return true;
        }
        let why = format!(
            "{}: {} members of size {s:.4} ({} Gaussians in its first), below {} × the largest group's objects ({largest:.4}): a speck, not an object; stays background",
            g.name,
            g.members.len(),
            g.members[0].gaussians.len(),
            o.min_object_fraction
        );
        progress(&why);
        refused.push(why);
        false
    });
}

#[cfg(test)]
mod tests;
