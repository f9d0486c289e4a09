//! Copies of an example found in the scene ([`from_example`] in the module docs of [`crate::discover`]):
//! FPFH pairs, RANSAC placements, ICP onto the scene, and every candidate checked as an instance.
use std::collections::HashMap;

use anyhow::Result;
use kiddo::SquaredEuclidean;
use rand::{Rng, SeedableRng};

use crate::instancing::options::{InstanceOptions, Status};
use crate::instancing::pose::InstanceReport;
use crate::instancing::pose::{register_and_check, registration_cloud, RenderCheck};
use crate::math::{sigmoid, tree};
use crate::model::scene::Scene;
use crate::register::{centroid, fpfh, icp, normals, object_size, umeyama_bounded, RegisterOptions, Sim3, FPFH_DIM};

use super::{find_support, DiscoverOptions, Discovery, FoundGroup, Member, Support};

/// Ids under which candidates meet the render check (which caches each id's own renders);
/// far above any instance id.
pub(crate) static CHECK_IDS: std::sync::atomic::AtomicU32 = std::sync::atomic::AtomicU32::new(1 << 30);

pub(crate) fn opaque(scene: &Scene, i: usize, min_opacity: f32) -> bool {
    sigmoid(scene.opacities[i]) >= min_opacity
}

pub(crate) fn f64s(p: [f32; 3]) -> [f64; 3] {
    p.map(|c| c as f64)
}

pub(crate) fn dist2(a: &[f64; 3], b: &[f64; 3]) -> f64 {
    (0..3).map(|k| (a[k] - b[k]).powi(2)).sum()
}

/// Voxel cells of a cloud: centroids and the indices (into the cloud) of each cell's points.
pub(crate) fn voxel_cells(points: &[[f64; 3]], voxel: f64) -> (Vec<[f64; 3]>, Vec<Vec<usize>>) {
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
pub(crate) fn edges_fit(a: &[[f64; 3]], b: &[[f64; 3]], ratio: f64, range: Option<(f64, f64)>) -> bool {
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
pub(crate) fn nearest_k(f: &[f64; FPFH_DIM], set: &[[f64; FPFH_DIM]], k: usize, skip: &[bool]) -> Vec<usize> {
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
pub(crate) fn object_cloud(
    part: &Scene,
    support: Option<&Support>,
    min_opacity: f32,
) -> (Vec<[f64; 3]>, Vec<[f64; 3]>) {
    if let Some(s) = support {
        let all: Vec<usize> = (0..part.len()).collect();
        if let Some(kept) = s.object_gaussians(part, &all, min_opacity) {
            return registration_cloud(&part.select(&kept), min_opacity);
        }
    }
    registration_cloud(part, min_opacity)
}

/// One reference's search: its points, features and reach, and the scene's available opaque
/// points (voxelised once; a voxel leaves the search when all its Gaussians are taken).
struct Search<'a> {
    scene: &'a Scene,
    support: Option<&'a Support>,
    io: InstanceOptions,
    reg: RegisterOptions,
    ref_scene: Scene,
    /// The reference's registration cloud (points and colours).
    e_pts: Vec<[f64; 3]>,
    e_rgb: Vec<[f64; 3]>,
    /// Its voxel centres, their FPFH features, their centroid, its size and reach (every
    /// Gaussian of it, floor patches included, from that centre).
    e: Vec<[f64; 3]>,
    fe: Vec<[f64; FPFH_DIM]>,
    e_centre: [f64; 3],
    size: f64,
    radius: f64,
    /// The scene's available opaque Gaussians (`pool`), their voxel centres, the pool members of
    /// each voxel and the voxels' features.
    pool: Vec<usize>,
    s: Vec<[f64; 3]>,
    cells: Vec<Vec<usize>>,
    fs: Vec<[f64; FPFH_DIM]>,
    /// Scale range of a placement (None: rigid), inlier distance.
    range: Option<(f64, f64)>,
    dist: f64,
}

/// Searches `available` Gaussians of `scene` for copies of the reference (`reference`: scene
/// indices) and checks each; accepted copies' Gaussians are taken out of `available`. Ids are
/// drawn from `next_id`; `progress` gets one line per candidate.
#[allow(clippy::too_many_arguments)]
pub(crate) fn search_copies(
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
    let Some(search) = Search::new(scene, reference, support, available, o, group, refused) else {
        return Ok(Vec::new());
    };
    let mut rng = rand_pcg::Pcg64::seed_from_u64(search.io.seed ^ 0x5eed);
    let mut found = Vec::new();
    // Placements refused so far (their centres): not proposed again.
    let mut tried: Vec<[f64; 3]> = Vec::new();
    'rounds: while found.len() < o.max_copies {
        let best = search.placements(available, &tried, o, &mut rng);
        if best.is_empty() {
            break;
        }
        for (inliers, x) in best.into_iter().take(o.placements_per_round) {
            let placed_centre = x.apply(&search.e_centre);
            tried.push(placed_centre);
            let Some(claim) = search.candidate(available, x, o) else { continue };
            let id = *next_id;
            let where_ = format!("[{:.3}, {:.3}, {:.3}]", placed_centre[0], placed_centre[1], placed_centre[2]);
            let part = scene.select(&claim);
            let (c_pts, c_rgb) = object_cloud(&part, support, search.io.min_opacity);
            if c_pts.len() < search.e_pts.len() / 4 {
                refused.push(format!(
                    "{group}: candidate at {where_}: {} opaque Gaussians where the reference has {}",
                    c_pts.len(),
                    search.e_pts.len()
                ));
                continue;
            }
            // The render check keys its cache by id: each candidate gets its own.
            let check_id = CHECK_IDS.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            let mut report = InstanceReport::new(group, id, reference.id, claim.len());
            let parts = [search.ref_scene.clone(), part];
            let (pose, status) = register_and_check(
                &parts,
                &[search.e_pts.clone(), c_pts],
                &[search.e_rgb.clone(), c_rgb],
                1,
                0,
                &search.reg,
                &search.io,
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
                search.e.len()
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

impl<'a> Search<'a> {
    /// The search's data, or None (with the reason in `refused` where it is the reference's)
    /// when the reference or the scene has too few points to search with.
    fn new(
        scene: &'a Scene,
        reference: &Member,
        support: Option<&'a Support>,
        available: &[bool],
        o: &DiscoverOptions,
        group: &str,
        refused: &mut Vec<String>,
    ) -> Option<Search<'a>> {
        // Shape-ambiguous copies also try turns about the support plane's normal.
        let io = InstanceOptions { up: o.instance.up.or(support.map(|s| s.normal)), ..o.instance.clone() };
        let ref_scene = scene.select(&reference.gaussians);
        let (e_pts, e_rgb) = object_cloud(&ref_scene, support, io.min_opacity);
        let size = object_size(&e_pts);
        let reg = io.register_options(size);
        let voxel = reg.voxel;
        let (e, _) = voxel_cells(&e_pts, voxel);
        if e.len() < 8 || size <= 0.0 {
            refused.push(format!("{group}: the reference has too few points to search with ({} voxels)", e.len()));
            return None;
        }
        let fe = fpfh(&e, &normals(&e, 2.0 * voxel, 30), 5.0 * voxel, 100);
        // The slab of the support plane takes no part in matching: each copy's own bottom is
        // claimed with it.
        let pool: Vec<usize> = (0..scene.len())
            .filter(|&i| available[i] && opaque(scene, i, io.min_opacity))
            .filter(|&i| support.is_none_or(|s| s.height(scene.means[i]) > 1.5 * s.thickness))
            .collect();
        let pool_pts: Vec<[f64; 3]> = pool.iter().map(|&i| f64s(scene.means[i])).collect();
        if pool_pts.len() < 8 {
            return None;
        }
        let (s, cells) = voxel_cells(&pool_pts, voxel);
        let fs = fpfh(&s, &normals(&s, 2.0 * voxel, 30), 5.0 * voxel, 100);
        let range = io.with_scale.then(|| (1.0 / (1.0 + io.accept.scale_tolerance), 1.0 + io.accept.scale_tolerance));
        let e_centre: [f64; 3] = centroid(&e).into();
        let radius = ref_scene.means.iter().map(|m| dist2(&f64s(*m), &e_centre).sqrt()).fold(0.0, f64::max);
        Some(Search {
            scene,
            support,
            dist: 1.5 * voxel,
            io,
            reg,
            ref_scene,
            e_pts,
            e_rgb,
            e,
            fe,
            e_centre,
            size,
            radius,
            pool,
            s,
            cells,
            fs,
            range,
        })
    }

    /// One round of RANSAC over FPFH pairs (each example voxel with its 4 nearest available
    /// scene features, triples drawn near each other): the placements whose probe points land on
    /// available scene points, one per place, most inliers (per mille) first.
    fn placements(
        &self,
        available: &[bool],
        tried: &[[f64; 3]],
        o: &DiscoverOptions,
        rng: &mut rand_pcg::Pcg64,
    ) -> Vec<(usize, Sim3)> {
        let (e, s, size, dist) = (&self.e, &self.s, self.size, self.dist);
        let gone: Vec<bool> = self.cells.iter().map(|m| m.iter().all(|&j| !available[self.pool[j]])).collect();
        let corr: Vec<(usize, usize)> = (0..e.len())
            .flat_map(|i| nearest_k(&self.fe[i], &self.fs, 4, &gone).into_iter().map(move |j| (i, j)))
            .collect();
        if corr.len() < 3 {
            return Vec::new();
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
            if !edges_fit(&a, &b, self.reg.edge_ratio, self.range) {
                continue;
            }
            let Some(x) = umeyama_bounded(&a, &b, self.range) else { continue };
            if a.iter().zip(&b).any(|(p, q)| dist2(&x.apply(p), q) > dist * dist) {
                continue;
            }
            let placed = x.apply(&self.e_centre);
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
                best.iter().position(|(_, y)| dist2(&y.apply(&self.e_centre), &placed) < (0.5 * size).powi(2))
            {
                if inliers > best[k].0 {
                    best[k] = (inliers, x);
                }
            } else {
                best.push((inliers, x));
            }
        }
        best.sort_by_key(|b| std::cmp::Reverse(b.0));
        best
    }

    /// A placement refined by ICP onto the available opaque scene points around it (the slab's
    /// too: the example's bottom meets them) and the Gaussians it claims: available ones near a
    /// placed reference Gaussian, less the floor around it. None when too few points are there.
    fn candidate(&self, available: &[bool], x: Sim3, o: &DiscoverOptions) -> Option<Vec<usize>> {
        let (scene, io, size, voxel) = (self.scene, &self.io, self.size, self.reg.voxel);
        let placed_centre = x.apply(&self.e_centre);
        let local: Vec<[f64; 3]> = (0..scene.len())
            .filter(|&i| available[i] && opaque(scene, i, io.min_opacity))
            .map(|i| f64s(scene.means[i]))
            .filter(|p| dist2(p, &placed_centre) <= (0.75 * size * x.scale).powi(2))
            .collect();
        if local.len() < 8 {
            return None;
        }
        let x = icp(&self.e_pts, &local, x, self.dist, 30, self.range, false);
        let x = icp(&self.e_pts, &local, x, 0.5 * voxel, 30, self.range, false);
        let placed: Vec<[f64; 3]> = self.ref_scene.means.iter().map(|m| x.apply(&f64s(*m))).collect();
        let t = tree(&placed);
        let reach = (o.claim_voxels * voxel * x.scale).powi(2);
        let claim: Vec<usize> = (0..scene.len())
            .filter(|&i| available[i])
            .filter(|&i| {
                let p = f64s(scene.means[i]);
                dist2(&p, &placed_centre) <= (1.05 * self.radius * x.scale).powi(2)
                    && t.nearest_one::<SquaredEuclidean>(&p).distance <= reach
            })
            .collect();
        let claim = self.support.and_then(|s| s.object_gaussians(scene, &claim, io.min_opacity)).unwrap_or(claim);
        Some(claim)
    }
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
