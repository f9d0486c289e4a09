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
pub mod run;

use std::collections::HashMap;

use anyhow::Result;
use kiddo::SquaredEuclidean;
use nalgebra::Vector3;
use rand::{Rng, SeedableRng};

use crate::instancing::template::{
    register_and_check, registration_cloud, InstanceOptions, InstanceReport, RenderCheck, Status,
};
use crate::math::{quat_to_mat, sigmoid, tree};
use crate::model::scene::Scene;
use crate::register::{
    centroid, fpfh, icp, median_spacing, normals, object_size, support_plane, umeyama_bounded, Sim3, FPFH_DIM,
};

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

/// Ids under which candidates meet the render check (which caches each id's own renders);
/// far above any instance id.
static CHECK_IDS: std::sync::atomic::AtomicU32 = std::sync::atomic::AtomicU32::new(1 << 30);

fn opaque(scene: &Scene, i: usize, min_opacity: f32) -> bool {
    sigmoid(scene.opacities[i]) >= min_opacity
}

fn f64s(p: [f32; 3]) -> [f64; 3] {
    p.map(|c| c as f64)
}

fn dist2(a: &[f64; 3], b: &[f64; 3]) -> f64 {
    (0..3).map(|k| (a[k] - b[k]).powi(2)).sum()
}

/// Voxel cells of a cloud: centroids and the indices (into the cloud) of each cell's points.
fn voxel_cells(points: &[[f64; 3]], voxel: f64) -> (Vec<[f64; 3]>, Vec<Vec<usize>>) {
    let mut cells: HashMap<[i64; 3], usize> = HashMap::new();
    let mut members: Vec<Vec<usize>> = Vec::new();
    for (j, p) in points.iter().enumerate() {
        let key = p.map(|c| (c / voxel).floor() as i64);
        let i = *cells.entry(key).or_insert_with(|| {
            members.push(Vec::new());
            members.len() - 1
        });
        members[i].push(j);
    }
    let centres = members
        .iter()
        .map(|m| {
            let mut c = [0.0; 3];
            for &j in m {
                for a in 0..3 {
                    c[a] += points[j][a] / m.len() as f64;
                }
            }
            c
        })
        .collect();
    (centres, members)
}

/// The sample's edges in `b` are those of `a` times one scale (each pair of ratios within
/// `ratio`), and that scale lies in `range` (1 without).
fn edges_fit(a: &[[f64; 3]], b: &[[f64; 3]], ratio: f64, range: Option<(f64, f64)>) -> bool {
    let mut k = Vec::with_capacity(3);
    for i in 0..a.len() {
        for j in i + 1..a.len() {
            let (x, y) = (dist2(&a[i], &a[j]).sqrt(), dist2(&b[i], &b[j]).sqrt());
            if x <= 0.0 {
                return false;
            }
            k.push(y / x);
        }
    }
    let lo = k.iter().copied().fold(f64::INFINITY, f64::min);
    let hi = k.iter().copied().fold(0.0, f64::max);
    let (min, max) = range.unwrap_or((1.0, 1.0));
    lo >= ratio * hi && lo >= ratio * min && hi * ratio <= max
}

/// The `k` nearest of `set` to `f` (Euclidean), nearest first; `skip` leaves entries out.
fn nearest_k(f: &[f64; FPFH_DIM], set: &[[f64; FPFH_DIM]], k: usize, skip: &[bool]) -> Vec<usize> {
    let mut best: Vec<(f64, usize)> = Vec::with_capacity(k + 1);
    for (j, g) in set.iter().enumerate() {
        if skip[j] {
            continue;
        }
        let d: f64 = f.iter().zip(g).map(|(a, b)| (a - b) * (a - b)).sum();
        if best.len() < k || d < best[k - 1].0 {
            let at = best.partition_point(|b| b.0 <= d);
            best.insert(at, (d, j));
            best.truncate(k);
        }
    }
    best.into_iter().map(|b| b.1).collect()
}

/// [`registration_cloud`] of `part`'s object Gaussians ([`Support::object_gaussians`]; all of
/// them where fewer than 16 stand above the plane's slab, or without a support plane): a patch
/// of floor is no part of an object's shape, its bottom is.
fn object_cloud(part: &Scene, support: Option<&Support>, min_opacity: f32) -> (Vec<[f64; 3]>, Vec<[f64; 3]>) {
    if let Some(s) = support {
        let all: Vec<usize> = (0..part.len()).collect();
        if let Some(kept) = s.object_gaussians(part, &all, min_opacity) {
            return registration_cloud(&part.select(&kept), min_opacity);
        }
    }
    registration_cloud(part, min_opacity)
}

/// Searches `available` Gaussians of `scene` for copies of the reference (`reference`: scene
/// indices) and checks each; accepted copies' Gaussians are taken out of `available`. Ids are
/// drawn from `next_id`; `progress` gets one line per candidate.
#[allow(clippy::too_many_arguments)]
fn search_copies(
    scene: &Scene,
    reference: &Member,
    support: Option<&Support>,
    group: &str,
    available: &mut [bool],
    o: &DiscoverOptions,
    render_check: &mut Option<&mut dyn RenderCheck>,
    next_id: &mut u32,
    refused: &mut Vec<String>,
    progress: &mut dyn FnMut(&str),
) -> Result<Vec<Member>> {
    // Shape-ambiguous copies also try turns about the support plane's normal.
    let io = &InstanceOptions { up: o.instance.up.or(support.map(|s| s.normal)), ..o.instance.clone() };
    let ref_scene = scene.select(&reference.gaussians);
    let (e_pts, e_rgb) = object_cloud(&ref_scene, support, io.min_opacity);
    let size = object_size(&e_pts);
    let reg = io.register_options(size);
    let voxel = reg.voxel;
    let (e, _) = voxel_cells(&e_pts, voxel);
    if e.len() < 8 || size <= 0.0 {
        refused.push(format!("{group}: the reference has too few points to search with ({} voxels)", e.len()));
        return Ok(Vec::new());
    }
    let fe = fpfh(&e, &normals(&e, 2.0 * voxel, 30), 5.0 * voxel, 100);
    // The scene's opaque available Gaussians, voxelised once; a voxel leaves the search when
    // all its Gaussians are taken.
    // The slab of the support plane takes no part in matching: each copy's own bottom is
    // claimed with it.
    let pool: Vec<usize> = (0..scene.len())
        .filter(|&i| available[i] && opaque(scene, i, io.min_opacity))
        .filter(|&i| support.is_none_or(|s| s.height(scene.means[i]) > 1.5 * s.thickness))
        .collect();
    let pool_pts: Vec<[f64; 3]> = pool.iter().map(|&i| f64s(scene.means[i])).collect();
    if pool_pts.len() < 8 {
        return Ok(Vec::new());
    }
    let (s, cells) = voxel_cells(&pool_pts, voxel);
    let fs = fpfh(&s, &normals(&s, 2.0 * voxel, 30), 5.0 * voxel, 100);
    let range = io.with_scale.then(|| (1.0 / (1.0 + io.accept.scale_tolerance), 1.0 + io.accept.scale_tolerance));
    let dist = 1.5 * voxel;
    let mut rng = rand_pcg::Pcg64::seed_from_u64(io.seed ^ 0x5eed);
    let mut found = Vec::new();
    // Placements refused so far (their centres): not proposed again.
    let mut tried: Vec<[f64; 3]> = Vec::new();
    let e_centre = centroid(&e);
    // The example's reach from that centre: every Gaussian of it (floor patches included).
    let radius = ref_scene.means.iter().map(|m| dist2(&f64s(*m), &e_centre.into()).sqrt()).fold(0.0, f64::max);
    'rounds: while found.len() < o.max_copies {
        let gone: Vec<bool> = cells.iter().map(|m| m.iter().all(|&j| !available[pool[j]])).collect();
        // Each example point paired with its 4 nearest scene features.
        let corr: Vec<(usize, usize)> =
            (0..e.len()).flat_map(|i| nearest_k(&fe[i], &fs, 4, &gone).into_iter().map(move |j| (i, j))).collect();
        if corr.len() < 3 {
            break;
        }
        // Correspondences binned by their scene point on a grid of the example's size.
        let cell = |p: &[f64; 3]| p.map(|c| (c / size).floor() as i64);
        let mut grid: HashMap<[i64; 3], Vec<usize>> = HashMap::new();
        for (c, &(_, j)) in corr.iter().enumerate() {
            grid.entry(cell(&s[j])).or_default().push(c);
        }
        let near = |p: &[f64; 3]| {
            let k = cell(p);
            let mut v = Vec::new();
            for dx in -1..=1 {
                for dy in -1..=1 {
                    for dz in -1..=1 {
                        if let Some(list) = grid.get(&[k[0] + dx, k[1] + dy, k[2] + dz]) {
                            v.extend_from_slice(list);
                        }
                    }
                }
            }
            v
        };
        let min_inliers = ((0.02 * e.len() as f64).ceil() as usize).max(6);
        // Placements are scored by the example points that land on an available scene point.
        let live: Vec<[f64; 3]> = (0..s.len()).filter(|&j| !gone[j]).map(|j| s[j]).collect();
        let live_tree = tree(&live);
        let stride = e.len().div_ceil(256);
        let probe: Vec<[f64; 3]> = e.iter().step_by(stride).copied().collect();
        let mut best: Vec<(usize, Sim3)> = Vec::new();
        for _ in 0..o.ransac_iterations {
            let c0 = rng.random_range(0..corr.len());
            let around = near(&s[corr[c0].1]);
            if around.len() < 3 {
                continue;
            }
            let c1 = around[rng.random_range(0..around.len())];
            let c2 = around[rng.random_range(0..around.len())];
            let idx = [c0, c1, c2];
            let a: Vec<[f64; 3]> = idx.iter().map(|&c| e[corr[c].0]).collect();
            let b: Vec<[f64; 3]> = idx.iter().map(|&c| s[corr[c].1]).collect();
            if (0..3).any(|i| (0..i).any(|k| corr[idx[i]].0 == corr[idx[k]].0 || corr[idx[i]].1 == corr[idx[k]].1)) {
                continue;
            }
            if !edges_fit(&a, &b, reg.edge_ratio, range) {
                continue;
            }
            let Some(x) = umeyama_bounded(&a, &b, range) else { continue };
            if a.iter().zip(&b).any(|(p, q)| dist2(&x.apply(p), q) > dist * dist) {
                continue;
            }
            let placed = x.apply(&e_centre.into());
            if tried.iter().any(|t| dist2(t, &placed) < (0.5 * size).powi(2)) {
                continue;
            }
            let mut hit = vec![false; e.len()];
            for &c in &around {
                let (i, j) = corr[c];
                if dist2(&x.apply(&e[i]), &s[j]) <= dist * dist {
                    hit[i] = true;
                }
            }
            if hit.iter().filter(|&&h| h).count() < min_inliers {
                continue;
            }
            let landed = probe
                .iter()
                .filter(|p| live_tree.nearest_one::<SquaredEuclidean>(&x.apply(p)).distance <= dist * dist)
                .count();
            let inliers = landed * 1000 / probe.len();
            if (inliers as f64) < 1000.0 * o.min_inlier_fraction {
                continue;
            }
            // One entry per placement (centres closer than half the size are one place).
            if let Some(k) =
                best.iter().position(|(_, y)| dist2(&y.apply(&e_centre.into()), &placed) < (0.5 * size).powi(2))
            {
                if inliers > best[k].0 {
                    best[k] = (inliers, x);
                }
            } else {
                best.push((inliers, x));
            }
        }
        best.sort_by_key(|b| std::cmp::Reverse(b.0));
        if best.is_empty() {
            break;
        }
        for (inliers, x) in best.into_iter().take(o.placements_per_round) {
            let placed_centre = x.apply(&e_centre.into());
            tried.push(placed_centre);
            // ICP of the example onto the available opaque scene points around the placement
            // (the slab's too: the example's bottom meets them).
            let local: Vec<[f64; 3]> = (0..scene.len())
                .filter(|&i| available[i] && opaque(scene, i, io.min_opacity))
                .map(|i| f64s(scene.means[i]))
                .filter(|p| dist2(p, &placed_centre) <= (0.75 * size * x.scale).powi(2))
                .collect();
            if local.len() < 8 {
                continue;
            }
            let x = icp(&e_pts, &local, x, dist, 30, range, false);
            let x = icp(&e_pts, &local, x, 0.5 * voxel, 30, range, false);
            // The candidate copy: available Gaussians near a placed reference Gaussian.
            let placed: Vec<[f64; 3]> = ref_scene.means.iter().map(|m| x.apply(&f64s(*m))).collect();
            let t = tree(&placed);
            let reach = (o.claim_voxels * voxel * x.scale).powi(2);
            let claim: Vec<usize> = (0..scene.len())
                .filter(|&i| available[i])
                .filter(|&i| {
                    let p = f64s(scene.means[i]);
                    dist2(&p, &placed_centre) <= (1.05 * radius * x.scale).powi(2)
                        && t.nearest_one::<SquaredEuclidean>(&p).distance <= reach
                })
                .collect();
            // Of those, the object's: the floor around it stays.
            let claim = support.and_then(|s| s.object_gaussians(scene, &claim, io.min_opacity)).unwrap_or(claim);
            let where_ = format!("[{:.3}, {:.3}, {:.3}]", placed_centre[0], placed_centre[1], placed_centre[2]);
            let part = scene.select(&claim);
            let (c_pts, c_rgb) = object_cloud(&part, support, io.min_opacity);
            if c_pts.len() < e_pts.len() / 4 {
                refused.push(format!(
                    "{group}: candidate at {where_}: {} opaque Gaussians where the reference has {}",
                    c_pts.len(),
                    e_pts.len()
                ));
                continue;
            }
            let id = *next_id;
            // The render check keys its cache by id: each candidate gets its own.
            let check_id = CHECK_IDS.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            let mut report = InstanceReport::new(group, id, reference.id, claim.len());
            let parts = [ref_scene.clone(), part];
            let (pose, status) = register_and_check(
                &parts,
                &[e_pts.clone(), c_pts],
                &[e_rgb.clone(), c_rgb],
                1,
                0,
                &reg,
                io,
                render_check,
                &mut report,
                group,
                &[reference.id, check_id],
            )?;
            report.relative = pose;
            report.status = status.clone();
            let scores = format!(
                "fitness {:.2} / {:.2}, scale {:.3}{}; placed with {:.0} % of {} points landing",
                report.check.fitness,
                report.check.fitness_reverse,
                pose.scale,
                report.render.map(|s| format!(", render IoU {:.2} PSNR {:.1} dB", s.iou, s.psnr)).unwrap_or_default(),
                inliers as f64 / 10.0,
                e.len()
            );
            match status {
                Status::Accepted => {
                    *next_id += 1;
                    for &i in &claim {
                        available[i] = false;
                    }
                    progress(&format!("{group}: copy {id} at {where_}, {} Gaussians ({scores})", claim.len()));
                    found.push(Member { id, gaussians: claim, relative: pose, report: Some(report) });
                    continue 'rounds;
                }
                other => {
                    let why = other.reason().unwrap_or("refused").to_string();
                    progress(&format!("{group}: candidate at {where_} refused: {why} ({scores})"));
                    refused.push(format!("{group}: candidate at {where_}: {why}"));
                }
            }
        }
        break;
    }
    Ok(found)
}

/// Finds the copies of the example (`example`: scene indices, the group's reference).
pub fn from_example(
    scene: &Scene,
    example: &[usize],
    o: &DiscoverOptions,
    mut render_check: Option<&mut dyn RenderCheck>,
    mut progress: impl FnMut(&str),
) -> Result<Discovery> {
    if example.is_empty() {
        anyhow::bail!("the example holds no Gaussian");
    }
    let mut available = vec![true; scene.len()];
    let mut example = example.to_vec();
    // A dominant support plane (a tenth of the scene's cells or more) belongs to no object: a
    // box drawn around an object holds some of it, the copies' surroundings too. The example
    // keeps its object Gaussians ([`Support::object_gaussians`]: those above the plane's slab
    // and its bottom inside their footprint), as `auto`'s clusters do, and every copy is then
    // cut from the floor alike.
    let mut support = find_support(scene, o, &mut progress).ok().filter(|s| s.share >= 0.1);
    if let Some(s) = support {
        match s.object_gaussians(scene, &example, o.instance.min_opacity) {
            Some(kept) => {
                if kept.len() < example.len() {
                    progress(&format!(
                        "the example leaves {} Gaussians on the support plane",
                        example.len() - kept.len()
                    ));
                }
                example = kept;
            }
            None => support = None,
        }
    }
    // The example grows by the rule that makes a copy of it: every available Gaussian within
    // `claim_voxels` registration voxels of one of its Gaussians (so that the two are cut from
    // their surroundings alike, e.g. both with the floor just around them).
    let ex_scene = scene.select(&example);
    let (pts, _) = object_cloud(&ex_scene, support.as_ref(), o.instance.min_opacity);
    let reach = o.claim_voxels * o.instance.register_options(object_size(&pts)).voxel;
    if reach > 0.0 && !example.is_empty() {
        let ex_means: Vec<[f64; 3]> = ex_scene.means.iter().map(|m| f64s(*m)).collect();
        let t = tree(&ex_means);
        let mut in_example = vec![false; scene.len()];
        for &i in &example {
            in_example[i] = true;
        }
        let grown: Vec<usize> = (0..scene.len())
            .filter(|&i| {
                in_example[i] || t.nearest_one::<SquaredEuclidean>(&f64s(scene.means[i])).distance <= reach * reach
            })
            .collect();
        example = support.and_then(|s| s.object_gaussians(scene, &grown, o.instance.min_opacity)).unwrap_or(grown);
    }
    for &i in &example {
        available[i] = false;
    }
    let reference = Member { id: 1, gaussians: example, relative: Sim3::identity(), report: None };
    let mut next_id = 2;
    let mut out = Discovery::default();
    let copies = search_copies(
        scene,
        &reference,
        support.as_ref(),
        "example",
        &mut available,
        o,
        &mut render_check,
        &mut next_id,
        &mut out.refused,
        &mut progress,
    )?;
    let mut members = vec![reference];
    members.extend(copies);
    out.groups.push(FoundGroup { name: "example".into(), members });
    Ok(out)
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

/// The scene's support plane: points p with normal·p − offset ≤ `thickness` lie on it; the
/// normal points to the side where more of the scene stands.
#[derive(Clone, Copy, Debug)]
pub struct Support {
    pub normal: Vector3<f64>,
    pub offset: f64,
    pub thickness: f64,
    /// Fraction of the scene's occupied cells (of `thickness`) on the plane.
    pub share: f64,
    /// An orthonormal basis of the plane (planar coordinates, footprints).
    basis: [Vector3<f64>; 2],
}

impl Support {
    /// The plane n·p = offset (n a unit normal pointing up), `thickness` thick.
    pub fn new(normal: Vector3<f64>, offset: f64, thickness: f64, share: f64) -> Support {
        let a = if normal[0].abs() < 0.9 { Vector3::x() } else { Vector3::y() };
        let u = normal.cross(&a).normalize();
        Support { normal, offset, thickness, share, basis: [u, normal.cross(&u)] }
    }

    /// Height of `p` above the plane.
    pub fn height(&self, p: [f32; 3]) -> f64 {
        self.normal.dot(&Vector3::from(f64s(p))) - self.offset
    }

    /// Coordinates of `p` in the plane.
    fn planar(&self, p: [f32; 3]) -> [f64; 2] {
        let q = Vector3::from(f64s(p));
        self.basis.map(|b| b.dot(&q))
    }

    /// Whether Gaussian `i` of `scene` lies in the footprint `hull` with its extent: its centre
    /// plus two standard deviations towards each edge's outside within half a plane thickness
    /// of the edge. An object's bottom passes (thin across its wall, which is an edge); a
    /// floor Gaussian whose centre falls just inside but which spreads out over the floor
    /// around does not.
    fn fits_inside(&self, hull: &[[f64; 2]], scene: &Scene, i: usize) -> bool {
        let [u, v] = self.basis;
        let q = self.planar(scene.means[i]);
        // Each edge: how far the centre lies beyond it (outward unit normal of a
        // counter-clockwise edge), and the outward normal in the world.
        let edges: Vec<(f64, Vector3<f64>)> = (0..hull.len())
            .filter_map(|k| {
                let (a, b) = (hull[k], hull[(k + 1) % hull.len()]);
                let len = ((b[0] - a[0]).powi(2) + (b[1] - a[1]).powi(2)).sqrt();
                let out = [(b[1] - a[1]) / len, -(b[0] - a[0]) / len];
                (len > 0.0).then(|| ((q[0] - a[0]) * out[0] + (q[1] - a[1]) * out[1], u * out[0] + v * out[1]))
            })
            .collect();
        let tolerance = 0.5 * self.thickness;
        if edges.iter().any(|e| e.0 > tolerance) {
            return false;
        }
        let r = quat_to_mat(scene.quats[i]);
        let s = scene.scales[i].map(|x| x.exp() as f64);
        edges.iter().all(|(beyond, d)| {
            let var: f64 = (0..3)
                .map(|c| {
                    let col = r.col(c);
                    (s[c] * (col.x as f64 * d.x + col.y as f64 * d.y + col.z as f64 * d.z)).powi(2)
                })
                .sum();
            beyond + 2.0 * var.sqrt() <= tolerance
        })
    }

    /// Whether `p` lies in the plane's slab: from half a thickness below the plane to 1.5
    /// thicknesses above it (what stands higher is clustered into objects).
    fn in_slab(&self, p: [f32; 3]) -> bool {
        let h = self.height(p);
        h > -0.5 * self.thickness && h <= 1.5 * self.thickness
    }

    /// The footprint of an object standing on the plane: the convex hull, in the plane, of its
    /// opaque Gaussians (of `part`, indices into `scene`) above the slab and less than 3
    /// thicknesses up — its lowest band, whose outline is its base. None for fewer than 3.
    fn footprint(&self, scene: &Scene, part: &[usize], min_opacity: f32) -> Option<Vec<[f64; 2]>> {
        let band: Vec<[f64; 2]> = part
            .iter()
            .filter(|&&i| opaque(scene, i, min_opacity))
            .filter(|&&i| (1.5 * self.thickness..=3.0 * self.thickness).contains(&self.height(scene.means[i])))
            .map(|&i| self.planar(scene.means[i]))
            .collect();
        let hull = convex_hull(band);
        (hull.len() >= 3).then_some(hull)
    }

    /// The Gaussians of `part` (indices into `scene`) that make up the object(s) standing
    /// there: those above the slab, and those in the slab inside their footprint — the
    /// object's bottom, down to where it meets the plane, where the floor around it lies
    /// outside. None where fewer than 16 stand above the slab.
    pub fn object_gaussians(&self, scene: &Scene, part: &[usize], min_opacity: f32) -> Option<Vec<usize>> {
        let above = |i: usize| self.height(scene.means[i]) > 1.5 * self.thickness;
        let up: Vec<usize> = part.iter().copied().filter(|&i| above(i)).collect();
        if up.len() < 16 {
            return None;
        }
        let Some(hull) = self.footprint(scene, &up, min_opacity) else { return Some(up) };
        Some(
            part.iter()
                .copied()
                .filter(|&i| above(i) || (self.in_slab(scene.means[i]) && self.fits_inside(&hull, scene, i)))
                .collect(),
        )
    }
}

/// Convex hull of 2D points, counter-clockwise (Andrew's monotone chain); collinear points
/// are left out.
fn convex_hull(mut p: Vec<[f64; 2]>) -> Vec<[f64; 2]> {
    p.sort_by(|a, b| a[0].total_cmp(&b[0]).then(a[1].total_cmp(&b[1])));
    p.dedup();
    if p.len() < 3 {
        return p;
    }
    let cross = |o: [f64; 2], a: [f64; 2], b: [f64; 2]| (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0]);
    let mut hull: Vec<[f64; 2]> = Vec::with_capacity(2 * p.len());
    for pass in 0..2 {
        let start = hull.len();
        let points: Box<dyn Iterator<Item = &[f64; 2]>> =
            if pass == 0 { Box::new(p.iter()) } else { Box::new(p.iter().rev()) };
        for &q in points {
            while hull.len() >= start + 2 && cross(hull[hull.len() - 2], hull[hull.len() - 1], q) <= 0.0 {
                hull.pop();
            }
            hull.push(q);
        }
        hull.pop();
    }
    hull
}

/// [`support_plane`] of the scene's opaque means, `o.plane_spacings` median spacings thick.
pub fn find_support(scene: &Scene, o: &DiscoverOptions, progress: &mut dyn FnMut(&str)) -> Result<Support> {
    let pts: Vec<[f64; 3]> =
        (0..scene.len()).filter(|&i| opaque(scene, i, o.instance.min_opacity)).map(|i| f64s(scene.means[i])).collect();
    if pts.len() < 3 {
        anyhow::bail!("the scene has too few opaque Gaussians ({}) to search", pts.len());
    }
    let thickness = o.plane_spacings * median_spacing(&pts);
    let (coarse, _) = voxel_cells(&pts, thickness);
    let Some((mut n, mut d, on)) = support_plane(&coarse, thickness, o.instance.seed) else {
        anyhow::bail!("no support plane found");
    };
    // Up: the side of the plane with more of the rest.
    let above = pts.iter().filter(|p| n.dot(&Vector3::from(**p)) - d > thickness).count();
    let below = pts.iter().filter(|p| n.dot(&Vector3::from(**p)) - d < -thickness).count();
    if below > above {
        (n, d) = (-n, -d);
    }
    // The plane is as thick as its Gaussians spread about it (4 × their median distance),
    // between a tenth of the search's thickness and all of it: a flat floor cuts off no more
    // of what stands on it than it must.
    let mut h: Vec<f64> =
        pts.iter().map(|p| (n.dot(&Vector3::from(*p)) - d).abs()).filter(|&h| h <= thickness).collect();
    h.sort_by(f64::total_cmp);
    let spread = h.get(h.len() / 2).copied().unwrap_or(thickness);
    let thickness = (4.0 * spread).clamp(0.1 * thickness, thickness);
    progress(&format!(
        "support plane: normal [{:.3}, {:.3}, {:.3}], {} of {} occupied cells on it ({:.4} thick)",
        n[0],
        n[1],
        n[2],
        on,
        coarse.len(),
        thickness
    ));
    Ok(Support::new(n, d, thickness, on as f64 / coarse.len() as f64))
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
    // Every Gaussian above the slab near a candidate's points (within one link) belongs to it,
    // and so do the slab's Gaussians inside its footprint (its bottom).
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
    out.groups = groups;
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn clusters_split_at_gaps_wider_than_the_link() {
        let line = |x0: f64, n: usize| (0..n).map(move |i| [x0 + 0.01 * i as f64, 0.0, 0.0]);
        let pts: Vec<[f64; 3]> = line(0.0, 50).chain(line(1.0, 30)).chain(line(0.6, 20)).collect();
        let c = clusters(&pts, 0.015);
        let sizes: Vec<usize> = c.iter().map(|c| c.len()).collect();
        assert_eq!(sizes, [50, 30, 20]);
        assert_eq!(clusters(&pts, 0.5).len(), 1);
    }

    #[test]
    fn the_convex_hull_holds_every_point_and_nothing_outside() {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(5);
        let pts: Vec<[f64; 2]> = (0..200).map(|_| [rng.random_range(-1.0..1.0), rng.random_range(-0.5..0.5)]).collect();
        let hull = convex_hull(pts.clone());
        assert!(hull.len() >= 4 && hull.len() < 40, "{} corners", hull.len());
        let inside = |q: [f64; 2]| {
            (0..hull.len()).all(|k| {
                let (a, b) = (hull[k], hull[(k + 1) % hull.len()]);
                (b[0] - a[0]) * (q[1] - a[1]) - (b[1] - a[1]) * (q[0] - a[0]) >= 0.0
            })
        };
        assert!(pts.iter().all(|&q| inside(q)), "counter-clockwise, every point inside");
        assert!(!inside([1.01, 0.0]) && !inside([0.0, -0.51]));
        assert!(convex_hull(vec![[0.0, 0.0], [1.0, 1.0], [2.0, 2.0]]).len() < 3, "collinear: no area");
    }

    #[test]
    fn an_object_keeps_its_bottom_and_leaves_the_floor_around_it() {
        // A floor at z = 0 (flat Gaussians 5 cm wide within ±4 mm; some centred just inside
        // the box's base, spreading out) and a 0.2 × 0.2 × 0.3 box standing on it, its walls
        // (Gaussians flat across them) down to the floor.
        let mut rng = rand_pcg::Pcg64::seed_from_u64(9);
        let mut scene = Scene::default();
        let mut truth = Vec::new();
        let mut push = |scene: &mut Scene, p: [f64; 3], scales: [f32; 3], object: bool| {
            scene.means.push(p.map(|c| c as f32));
            scene.scales.push(scales);
            scene.quats.push([1.0, 0.0, 0.0, 0.0]);
            scene.opacities.push(3.0);
            scene.sh.extend([0.5; 3]);
            truth.push(object);
        };
        for _ in 0..3000 {
            let p: [f64; 3] =
                [rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0), rng.random_range(-0.004..0.004)];
            if p[0].abs() > 0.1 || p[1].abs() > 0.1 {
                push(&mut scene, p, [-3.0, -3.0, -8.0], false);
            }
        }
        for k in 0..20 {
            let a = -0.09 + 0.009 * k as f64;
            push(&mut scene, [0.095, a, 0.0], [-3.0, -3.0, -8.0], false);
            push(&mut scene, [a, -0.095, 0.0], [-3.0, -3.0, -8.0], false);
        }
        for _ in 0..2000 {
            let (a, z) = (rng.random_range(-0.1..0.1), rng.random_range(0.0..0.3));
            let (p, scales) = match rng.random_range(0..4) {
                0 => ([0.1, a, z], [-8.0, -5.0, -5.0]),
                1 => ([-0.1, a, z], [-8.0, -5.0, -5.0]),
                2 => ([a, 0.1, z], [-5.0, -8.0, -5.0]),
                _ => ([a, -0.1, z], [-5.0, -8.0, -5.0]),
            };
            push(&mut scene, p, scales, true);
        }
        let support = Support::new(Vector3::z(), 0.0, 0.02, 0.5);
        // The part: the box and the floor within 5 cm of it.
        let part: Vec<usize> =
            (0..scene.len()).filter(|&i| scene.means[i][0].abs() < 0.15 && scene.means[i][1].abs() < 0.15).collect();
        let kept = support.object_gaussians(&scene, &part, 0.5).unwrap();
        let box_all = truth.iter().filter(|&&t| t).count();
        assert!(kept.iter().all(|&i| truth[i]), "no floor Gaussian kept");
        assert!(kept.len() * 100 >= box_all * 98, "{} of {box_all} box Gaussians kept", kept.len());
        assert!(part.iter().any(|&i| !truth[i]), "the part holds floor");
    }

    #[test]
    fn edges_fit_needs_one_scale_in_range() {
        let a = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 2.0, 0.0]];
        let b = a.map(|p| p.map(|c| 1.1 * c + 3.0));
        assert!(edges_fit(&a, &b, 0.9, Some((0.8, 1.25))));
        let far = a.map(|p| p.map(|c| 1.3 * c));
        assert!(!edges_fit(&a, &far, 0.9, None), "rigid: scale 1.3 is refused");
        let mut c = b;
        c[2][1] *= 1.5;
        assert!(!edges_fit(&a, &c, 0.9, Some((0.8, 1.25))), "no common scale");
    }
}
