//! Pose synchronisation of a group: every accepted instance was registered onto the group's
//! reference alone, so its pose carries the errors of two reconstructions (its own and the
//! reference's) seen in its own views. Registering the accepted instances onto each other too
//! gives every pose several independent estimates (instance → another instance → reference);
//! their least-squares mean is closer to the truth than any one of them (rotation averaging,
//! Hartley, Trumpf, Dai & Li, "Rotation averaging", IJCV 2013: the chordal L2 mean, solved here
//! by block coordinate descent over the instances).
//!
//! On two demo plain scenes (ducks ~30 px wide) the five registrations onto the reference were
//! 0.2–3.7° off the ground truth, the worst 3.7° and 3.4°; synchronised, 0.3–1.8°
//! (BENCHMARKS.md, "Pose synchronisation").
use anyhow::Result;
use nalgebra::Vector3;

use crate::register::{centroid, Sim3};

/// Rounds of block coordinate descent (each instance's pose, in turn, becomes the mean of
/// its estimates under the others' current poses); a round costs microseconds.
const ROUNDS: usize = 100;

/// Accepted instances besides the reference needed to synchronise. With two, each pose has
/// two estimates, one of them through the other instance's registration too: the mean gains
/// little (a quarter of the variance at best), and on the fruit packages of the robustness study,
/// whose smaller copies come out blurrier, one biased pair moved both poses away from the truth
/// (BENCHMARKS.md). From three on, every pose has three or more estimates.
pub const MIN_ACCEPTED: usize = 3;

/// A registration that disagrees with the poses synchronised from it and the others by more
/// than this rotation (degrees) or this fraction of the reference's size at the instance is
/// wrong: the cycles through it do not close. The goal a pose must meet is 5° / 5 % of the
/// ground truth.
pub const RESIDUAL_DEG: f64 = 5.0;
pub const RESIDUAL_FRACTION: f64 = 0.05;
/// A cycle of three registrations (an edge and the two onto the reference) closes within
/// this multiple of those limits: each may be off by its share, and the errors add up.
pub const CYCLE_FACTOR: f64 = 2.0;

/// One pairwise pose: instance `from`'s world → instance `to`'s world.
#[derive(Clone, Copy, Debug)]
struct Measurement {
    from: usize,
    to: usize,
    pose: Sim3,
}

/// What synchronisation did to one instance's pose.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Synchronised {
    /// The synchronised pose (instance world → reference world).
    pub pose: Sim3,
    /// Its rotation away from the registration onto the reference alone (degrees).
    pub moved_deg: f64,
    /// The largest rotation between it and one of its estimates (degrees): how far the
    /// registrations through other instances disagreed.
    pub spread_deg: f64,
    /// Registrations that gave it an estimate (its own onto the reference, if kept, and one
    /// per kept edge).
    pub estimates: usize,
}

/// A registration refused because a cycle through it did not close.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RefusedEdge {
    pub from: usize,
    /// The reference for an instance's own registration onto it.
    pub to: usize,
    /// Its disagreement with the poses synchronised from the others (degrees, size fraction).
    pub rotation_deg: f64,
    pub translation_fraction: f64,
}

/// The cycle instance a → instance b → the reference, against a → the reference directly.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Cycle {
    pub a: usize,
    pub b: usize,
    pub rotation_deg: f64,
    pub translation_fraction: f64,
}

impl Cycle {
    pub fn closes(&self) -> bool {
        self.rotation_deg <= CYCLE_FACTOR * RESIDUAL_DEG
            && self.translation_fraction <= CYCLE_FACTOR * RESIDUAL_FRACTION
    }
}

/// The synchronisation of a group over its pose graph.
#[derive(Clone, Debug, Default)]
pub struct Graph {
    /// Per instance: the synchronised pose (None for the reference and the instances with no
    /// estimate left).
    pub poses: Vec<Option<Synchronised>>,
    /// Every triangle of an edge with the two registrations onto the reference, before any
    /// registration was refused.
    pub cycles: Vec<Cycle>,
    /// Registrations refused, in the order they were (the worst first).
    pub refused: Vec<RefusedEdge>,
    /// Edges registered (pairs besides the registrations onto the reference).
    pub edges: usize,
}

/// The edges of a group's pose graph besides every accepted instance's registration onto the
/// reference `r`: each accepted instance paired with its `neighbours` nearest other accepted
/// instances (not the reference) by `signature` (a cheap descriptor, e.g. [`size_signature`]),
/// each pair once, (lower index, higher). Every instance then closes at least `neighbours`
/// triangles with the reference, and a registration that disagrees with its others can be
/// told from them; the work grows with the instances, not with their pairs.
pub fn candidate_edges(signature: &[Vec<f64>], accepted: &[usize], r: usize, neighbours: usize) -> Vec<(usize, usize)> {
    let others: Vec<usize> = accepted.iter().copied().filter(|&k| k != r).collect();
    let dist = |a: usize, b: usize| signature[a].iter().zip(&signature[b]).map(|(x, y)| (x - y).powi(2)).sum::<f64>();
    let mut edges = std::collections::BTreeSet::new();
    for &a in &others {
        let mut near: Vec<usize> = others.iter().copied().filter(|&b| b != a).collect();
        near.sort_by(|&x, &y| dist(a, x).total_cmp(&dist(a, y)).then(x.cmp(&y)));
        for &b in near.iter().take(neighbours) {
            edges.insert((a.min(b), a.max(b)));
        }
    }
    edges.into_iter().collect()
}

/// A cloud's size signature: the logarithms of its spreads along its principal axes (largest
/// first) and of a quarter of its point count. Two reconstructions of one object seen alike
/// (as completely, from similar sides) are near; a registration between them has the most to
/// match.
pub fn size_signature(points: &[[f64; 3]]) -> Vec<f64> {
    let c = centroid(points);
    let n = points.len().max(1) as f64;
    let cov = points.iter().fold(nalgebra::Matrix3::zeros(), |m, p| {
        let d = Vector3::from(*p) - c;
        m + d * d.transpose() / n
    });
    let mut e: Vec<f64> = cov.symmetric_eigenvalues().iter().map(|v| v.max(1e-12).sqrt().ln()).collect();
    e.sort_by(|a, b| b.total_cmp(a));
    e.push((n / 4.0).ln() / 4.0);
    e
}

/// Synchronises the poses `relative[k]` (instance k → the reference `r`; None: not accepted)
/// of a group's accepted instances over a sparse pose graph (with fewer than [`MIN_ACCEPTED`]
/// besides the reference every pose is None). Each `edges` pair (a, b) of accepted instances
/// other than the reference is registered by `register(a, b, start)` (a's world → b's world,
/// from the pose the two registrations imply, `start = relative[b]⁻¹ ∘ relative[a]`; None: no
/// estimate). Every pose becomes the mean ([`Sim3::mean`], about the instance's centroid in
/// `opaque`) of its estimates: the direct registration and one through each edge. Then the
/// registration that disagrees most with the synchronised poses is refused while one
/// disagrees by more than [`RESIDUAL_DEG`] or [`RESIDUAL_FRACTION`] of `size` (a wrong edge, or a
/// wrong registration onto the reference that its cycles outvote), and the rest synchronised
/// again. The caller checks the poses before keeping them.
pub fn synchronise(
    opaque: &[Vec<[f64; 3]>],
    r: usize,
    relative: &[Option<Sim3>],
    edges: &[(usize, usize)],
    size: f64,
    mut register: impl FnMut(usize, usize, Sim3) -> Result<Option<Sim3>>,
) -> Result<Graph> {
    let n = relative.len();
    let accepted: Vec<usize> = (0..n).filter(|&k| k != r && relative[k].is_some()).collect();
    let mut out = Graph { poses: vec![None; n], ..Default::default() };
    if accepted.len() < MIN_ACCEPTED {
        return Ok(out);
    }
    let direct = |k: usize| relative[k].expect("accepted");
    let mut measured: Vec<Measurement> =
        accepted.iter().map(|&k| Measurement { from: k, to: r, pose: direct(k) }).collect();
    for &(a, b) in edges {
        if a == r || b == r || relative[a].is_none() || relative[b].is_none() {
            continue;
        }
        out.edges += 1;
        if let Some(pose) = register(a, b, direct(b).inverse().compose(&direct(a)))? {
            measured.push(Measurement { from: a, to: b, pose });
        }
    }
    let centres: Vec<Vector3<f64>> = opaque.iter().map(|p| centroid(p)).collect();
    // How far x (k's world → the reference's) and y disagree at k's centre.
    let gap = |x: &Sim3, y: &Sim3, k: usize| {
        let c = [centres[k].x, centres[k].y, centres[k].z];
        let (p, q) = (Vector3::from(x.apply(&c)), Vector3::from(y.apply(&c)));
        (x.rotation_error_deg(y), (p - q).norm() / size.max(1e-12))
    };
    for m in &measured[accepted.len()..] {
        let (rotation_deg, translation_fraction) = gap(&direct(m.to).compose(&m.pose), &direct(m.from), m.from);
        out.cycles.push(Cycle { a: m.from, b: m.to, rotation_deg, translation_fraction });
    }
    loop {
        let pose = solve(&measured, relative, r, &accepted, &centres);
        // Each registration's disagreement with the others' poses, in units of its limits.
        let worst = measured
            .iter()
            .enumerate()
            .filter_map(|(i, m)| {
                let (Some(to), Some(from)) = (pose[m.to], pose[m.from]) else { return None };
                let (deg, frac) = gap(&to.compose(&m.pose), &from, m.from);
                Some((i, deg, frac, (deg / RESIDUAL_DEG).max(frac / RESIDUAL_FRACTION)))
            })
            .max_by(|a, b| a.3.total_cmp(&b.3));
        match worst {
            Some((i, rotation_deg, translation_fraction, w)) if w > 1.0 => {
                let m = measured.remove(i);
                out.refused.push(RefusedEdge { from: m.from, to: m.to, rotation_deg, translation_fraction });
            }
            _ => {
                for &k in &accepted {
                    let Some(p) = pose[k] else { continue };
                    let est = estimates(&measured, &pose, k);
                    let spread_deg = est.iter().map(|e| e.rotation_error_deg(&p)).fold(0.0, f64::max);
                    out.poses[k] = Some(Synchronised {
                        pose: p,
                        moved_deg: p.rotation_error_deg(&direct(k)),
                        spread_deg,
                        estimates: est.len(),
                    });
                }
                return Ok(out);
            }
        }
    }
}

/// The estimates of instance k's pose (k's world → the reference's) that the measurements
/// touching k give under the current `pose`s (None: unknown).
fn estimates(measured: &[Measurement], pose: &[Option<Sim3>], k: usize) -> Vec<Sim3> {
    measured
        .iter()
        .filter_map(|m| {
            if m.from == k {
                Some(pose[m.to]?.compose(&m.pose))
            } else if m.to == k {
                Some(pose[m.from]?.compose(&m.pose.inverse()))
            } else {
                None
            }
        })
        .collect()
}

/// The poses that the `measured` registrations give: the reference fixed at the identity, the
/// others found by breadth-first search from it (None: no path), then block coordinate descent
/// to the mean of their estimates ([`ROUNDS`]).
fn solve(
    measured: &[Measurement],
    relative: &[Option<Sim3>],
    r: usize,
    accepted: &[usize],
    centres: &[Vector3<f64>],
) -> Vec<Option<Sim3>> {
    let mut pose: Vec<Option<Sim3>> = vec![None; relative.len()];
    pose[r] = Some(Sim3::identity());
    let mut queue = std::collections::VecDeque::from([r]);
    while let Some(k) = queue.pop_front() {
        for m in measured {
            let (next, x) = if m.to == k && pose[m.from].is_none() {
                (m.from, pose[k].expect("reached").compose(&m.pose))
            } else if m.from == k && pose[m.to].is_none() {
                (m.to, pose[k].expect("reached").compose(&m.pose.inverse()))
            } else {
                continue;
            };
            // The direct registration starts where it has one (the first estimate otherwise).
            pose[next] = Some(match measured.iter().find(|d| d.from == next && d.to == r) {
                Some(d) => d.pose,
                None => x,
            });
            queue.push_back(next);
        }
    }
    for _ in 0..ROUNDS {
        for &k in accepted {
            if pose[k].is_some() {
                pose[k] = Sim3::mean(&estimates(measured, &pose, k), &centres[k]).or(pose[k]);
            }
        }
    }
    pose
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Rotation3, Vector3};
    use rand::Rng;

    fn turn(axis: [f64; 3], deg: f64) -> Sim3 {
        let axis = nalgebra::Unit::new_normalize(Vector3::from(axis));
        Sim3 { rotation: *Rotation3::from_axis_angle(&axis, deg.to_radians()).matrix(), ..Sim3::identity() }
    }

    /// `n` instances in a row, turned every way (object → world), four points each; every
    /// registration of a pair lands on the true relative pose turned by `noise_deg` about the
    /// instance's centre, about an axis of that pair (two reconstructions never agree exactly).
    struct Group {
        truth: Vec<Sim3>,
        bias: Vec<Vec<Sim3>>,
        opaque: Vec<Vec<[f64; 3]>>,
    }

    impl Group {
        fn new(n: usize, noise_deg: f64, seed: u64) -> Group {
            let mut rng = rand_pcg::Pcg64::new(seed as u128, 11);
            let mut random_turn = |deg: f64| {
                let axis = [rng.random::<f64>() - 0.5, rng.random::<f64>() - 0.5, rng.random::<f64>() - 0.5];
                turn(axis, deg)
            };
            let truth: Vec<Sim3> =
                (0..n).map(|k| Sim3 { translation: Vector3::new(k as f64, 0.0, 0.0), ..random_turn(40.0) }).collect();
            let bias = (0..n).map(|_| (0..n).map(|_| random_turn(noise_deg)).collect()).collect();
            let opaque = (0..n)
                .map(|k| {
                    (0..4)
                        .map(|i| truth[k].apply(&[0.1 * (i & 1) as f64, 0.1 * (i >> 1) as f64, 0.05 * i as f64]))
                        .collect()
                })
                .collect();
            Group { truth, bias, opaque }
        }

        /// a's world → b's world as a registration finds it.
        fn registered(&self, a: usize, b: usize) -> Sim3 {
            self.truth[b].compose(&self.truth[a].inverse()).compose(&self.bias[a][b].about(&centroid(&self.opaque[a])))
        }

        fn true_pose(&self, k: usize, r: usize) -> Sim3 {
            self.truth[r].compose(&self.truth[k].inverse())
        }

        /// Every registration onto reference 0 (None where `refused`).
        fn relative(&self) -> Vec<Option<Sim3>> {
            (0..self.truth.len()).map(|k| Some(if k == 0 { Sim3::identity() } else { self.registered(k, 0) })).collect()
        }

        /// Edges: each instance besides the reference with the next two in the row.
        fn ring(&self) -> Vec<(usize, usize)> {
            let others: Vec<usize> = (1..self.truth.len()).collect();
            let sig: Vec<Vec<f64>> = (0..self.truth.len()).map(|k| vec![k as f64]).collect();
            candidate_edges(&sig, &others, 0, 2)
        }
    }

    #[test]
    fn synchronised_poses_are_closer_to_the_truth_than_the_registrations_alone() {
        let g = Group::new(6, 3.0, 7);
        let relative = g.relative();
        let edges = g.ring();
        let mut pairs = 0;
        let graph = synchronise(&g.opaque, 0, &relative, &edges, 0.2, |a, b, start| {
            pairs += 1;
            // The start is what the two registrations imply: within their two errors.
            let x = g.registered(a, b);
            assert!(start.rotation_error_deg(&x) < 9.0, "{}", start.rotation_error_deg(&x));
            Ok(Some(x))
        })
        .unwrap();
        assert_eq!(pairs, edges.len());
        assert!(pairs <= 2 * 5, "{pairs} edges for five instances: two each at most");
        assert!(graph.poses[0].is_none());
        assert!(graph.refused.is_empty(), "{:?}", graph.refused);
        assert!(graph.cycles.iter().all(|c| c.closes()), "{:?}", graph.cycles);
        let (mut before, mut after) = (0.0, 0.0);
        for (k, alone) in relative.iter().enumerate().skip(1) {
            let t = g.true_pose(k, 0);
            let s = graph.poses[k].expect("synchronised");
            before += alone.unwrap().rotation_error_deg(&t);
            after += s.pose.rotation_error_deg(&t);
            assert!(s.spread_deg > 0.0 && s.moved_deg > 0.0 && s.estimates >= 3, "{s:?}");
        }
        // Measured: 1.70° against 3.00° (every pair registered: 1.49°).
        assert!(after < 0.75 * before, "mean error {:.2}° synchronised, {:.2}° alone", after / 5.0, before / 5.0);
    }

    #[test]
    fn a_wrong_edge_is_caught_by_its_cycle_and_refused() {
        let g = Group::new(8, 1.0, 3);
        let relative = g.relative();
        let edges = g.ring();
        let wrong = edges[3];
        let graph = synchronise(&g.opaque, 0, &relative, &edges, 0.2, |a, b, _| {
            let x = g.registered(a, b);
            // A registration of (a, b) that landed on another pose: 40° off.
            Ok(Some(if (a, b) == wrong {
                x.compose(&turn([0.0, 1.0, 0.2], 40.0).about(&centroid(&g.opaque[a])))
            } else {
                x
            }))
        })
        .unwrap();
        let open: Vec<&Cycle> = graph.cycles.iter().filter(|c| !c.closes()).collect();
        assert_eq!(open.len(), 1, "{:?}", graph.cycles);
        assert_eq!((open[0].a, open[0].b), wrong);
        assert!(open[0].rotation_deg > 30.0, "{:?}", open[0]);
        assert_eq!(graph.refused.len(), 1, "{:?}", graph.refused);
        assert_eq!((graph.refused[0].from, graph.refused[0].to), wrong);
        for k in 1..8 {
            let e = graph.poses[k].expect("synchronised").pose.rotation_error_deg(&g.true_pose(k, 0));
            assert!(e < 2.0, "instance {k}: {e:.2}° off");
        }
    }

    #[test]
    fn a_wrong_registration_onto_the_reference_is_outvoted_by_its_cycles() {
        let g = Group::new(8, 1.0, 5);
        let mut relative = g.relative();
        let bad = 4;
        let c = centroid(&g.opaque[bad]);
        // Instance 4's own registration landed 35° off (a symmetric object's other side).
        relative[bad] = Some(relative[bad].unwrap().compose(&turn([0.0, 0.0, 1.0], 35.0).about(&c)));
        let edges = g.ring();
        let graph = synchronise(&g.opaque, 0, &relative, &edges, 0.2, |a, b, _| Ok(Some(g.registered(a, b)))).unwrap();
        // Its cycles do not close, the others' do.
        for cycle in &graph.cycles {
            assert_eq!(cycle.closes(), cycle.a != bad && cycle.b != bad, "{cycle:?}");
        }
        assert_eq!(graph.refused.len(), 1, "{:?}", graph.refused);
        assert_eq!((graph.refused[0].from, graph.refused[0].to), (bad, 0));
        let s = graph.poses[bad].expect("its pose comes from its neighbours");
        assert!(s.pose.rotation_error_deg(&g.true_pose(bad, 0)) < 2.0, "{s:?}");
        assert!(s.moved_deg > 30.0, "{s:?}");
    }

    #[test]
    fn the_graph_grows_with_the_instances_not_their_pairs() {
        for n in [10, 20, 40] {
            let mut rng = rand_pcg::Pcg64::new(n as u128, 3);
            let sig: Vec<Vec<f64>> = (0..n).map(|_| vec![rng.random::<f64>(), rng.random::<f64>()]).collect();
            let accepted: Vec<usize> = (0..n).collect();
            let edges = candidate_edges(&sig, &accepted, 0, 2);
            assert!(edges.len() <= 2 * (n - 1), "{n} instances: {} edges", edges.len());
            for k in 1..n {
                let degree = edges.iter().filter(|e| e.0 == k || e.1 == k).count();
                assert!(degree >= 2, "instance {k}: {degree} edges");
            }
            assert!(edges.iter().all(|&(a, b)| a < b && a != 0));
        }
    }

    #[test]
    fn two_accepted_instances_besides_the_reference_are_left_alone() {
        let opaque = vec![vec![[0.0; 3]]; 4];
        let relative = vec![Some(Sim3::identity()), Some(Sim3::identity()), None, Some(Sim3::identity())];
        let out = synchronise(&opaque, 0, &relative, &[(1, 3)], 1.0, |_, _, _| panic!("no pair to register")).unwrap();
        assert!(out.poses.iter().all(|s| s.is_none()));
    }

    #[test]
    fn a_size_signature_tells_a_partial_reconstruction_from_a_whole_one() {
        let mut rng = rand_pcg::Pcg64::new(1, 1);
        let whole: Vec<[f64; 3]> =
            (0..800).map(|_| [rng.random::<f64>(), 0.5 * rng.random::<f64>(), 0.3 * rng.random::<f64>()]).collect();
        let turned: Vec<[f64; 3]> = whole.iter().map(|p| turn([1.0, 2.0, 0.5], 70.0).apply(p)).collect();
        let half: Vec<[f64; 3]> = whole.iter().copied().filter(|p| p[0] < 0.5).collect();
        let d = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(x, y)| (x - y).powi(2)).sum::<f64>();
        let (sw, st, sh) = (size_signature(&whole), size_signature(&turned), size_signature(&half));
        assert!(d(&sw, &st) < 1e-9, "a turn does not change it");
        assert!(d(&sw, &sh) > 0.1, "{sw:?} {sh:?}");
    }
}
