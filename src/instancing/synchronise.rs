//! Pose synchronisation of a group: every accepted instance was registered onto the group's
//! reference alone, so its pose carries the errors of two reconstructions (its own and the
//! reference's) seen in its own views. Registering the accepted instances onto each other too
//! gives every pose several independent estimates (instance → another instance → reference);
//! their least-squares mean is closer to the truth than any one of them (rotation averaging,
//! Hartley, Trumpf, Dai & Li, "Rotation averaging", IJCV 2013: the chordal L2 mean, solved here
//! by block coordinate descent over the instances).
//!
//! On the demo (ducks ~30 px wide) the five registrations onto the reference were 0.9–3.7° off
//! the ground truth; synchronised, 0.6–1.8° (BENCHMARKS.md, "The demo").
use anyhow::Result;

use crate::instancing::template::{refine_pose, RenderCheck};
use crate::model::scene::Scene;
use crate::register::{centroid, object_size, Sim3};

/// Rounds of block coordinate descent (each instance's pose, in turn, becomes the mean of
/// its estimates under the others' current poses). The demo converges in under 20.
const ROUNDS: usize = 100;

/// Accepted instances besides the reference needed to synchronise. With two, each pose has
/// two estimates, one of them through the other instance's registration too: the mean gains
/// little (a quarter of the variance at best), and on the fruit packages of the robustness study,
/// whose smaller copies come out blurrier, one biased pair moved both poses away from the truth
/// (BENCHMARKS.md). From three on, every pose has three or more estimates.
pub const MIN_ACCEPTED: usize = 3;

/// One pairwise pose: instance `from`'s world → instance `to`'s world.
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
}

/// Synchronises the poses `relative[k]` (instance k → the reference `r`; None: not accepted)
/// of a group's accepted instances (with fewer than [`MIN_ACCEPTED`] besides the reference
/// every entry is None). Every pair (a, b) of accepted instances other
/// than the reference is registered by refining a → b from the pose the two registrations
/// imply (`relative[b]⁻¹ ∘ relative[a]`) against a's views ([`refine_pose`], steps from 1°);
/// then every pose becomes the mean ([`Sim3::mean`], about the instance's centroid) of its
/// estimates: the direct registration and one through each other instance. Returns, per
/// instance, the synchronised pose (None for the reference and the instances not accepted);
/// the caller checks them before keeping them.
#[allow(clippy::too_many_arguments)]
pub fn synchronise(
    rc: &mut dyn RenderCheck,
    parts: &[Scene],
    opaque: &[Vec<[f64; 3]>],
    ids: &[u32],
    r: usize,
    relative: &[Option<Sim3>],
    rigid: bool,
) -> Result<Vec<Option<Synchronised>>> {
    let accepted: Vec<usize> = (0..parts.len()).filter(|&k| k != r && relative[k].is_some()).collect();
    let mut out = vec![None; parts.len()];
    if accepted.len() < MIN_ACCEPTED {
        return Ok(out);
    }
    let direct = |k: usize| relative[k].expect("accepted");
    let mut measured: Vec<Measurement> =
        accepted.iter().map(|&k| Measurement { from: k, to: r, pose: direct(k) }).collect();
    for (i, &a) in accepted.iter().enumerate() {
        for &b in &accepted[i + 1..] {
            let start = direct(b).inverse().compose(&direct(a));
            let Some(score) = rc.score(&parts[b], &parts[a], ids[a], &start)? else { continue };
            let (pose, _) = refine_pose(
                rc,
                &parts[b],
                &parts[a],
                ids[a],
                start,
                score,
                centroid(&opaque[b]),
                object_size(&opaque[b]),
                rigid,
                1..4,
            )?;
            measured.push(Measurement { from: a, to: b, pose });
        }
    }
    let mut pose: Vec<Sim3> = (0..parts.len()).map(|k| relative[k].unwrap_or_else(Sim3::identity)).collect();
    let estimates = |pose: &[Sim3], k: usize| -> Vec<Sim3> {
        measured
            .iter()
            .filter_map(|m| {
                if m.from == k {
                    Some(pose[m.to].compose(&m.pose))
                } else if m.to == k {
                    Some(pose[m.from].compose(&m.pose.inverse()))
                } else {
                    None
                }
            })
            .collect()
    };
    for _ in 0..ROUNDS {
        for &k in &accepted {
            pose[k] = Sim3::mean(&estimates(&pose, k), &centroid(&opaque[k])).unwrap_or(pose[k]);
        }
    }
    for &k in &accepted {
        let spread_deg = estimates(&pose, k).iter().map(|e| e.rotation_error_deg(&pose[k])).fold(0.0, f64::max);
        out[k] = Some(Synchronised { pose: pose[k], moved_deg: pose[k].rotation_error_deg(&direct(k)), spread_deg });
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::instancing::template::RenderScore;
    use nalgebra::{Rotation3, Vector3};

    fn turn(axis: [f64; 3], deg: f64) -> Sim3 {
        let axis = nalgebra::Unit::new_normalize(Vector3::from(axis));
        Sim3 { rotation: *Rotation3::from_axis_angle(&axis, deg.to_radians()).matrix(), ..Sim3::identity() }
    }

    /// A render check whose pictures prefer, for each (instance, reference) pair, the true
    /// relative pose turned by a bias of that pair about the instance's centre (two
    /// reconstructions never agree exactly): its score falls with the angle from that preferred
    /// pose and the distance between where the two put the instance's centre.
    struct Biased {
        /// Object → world of each instance.
        truth: Vec<Sim3>,
        bias: std::collections::HashMap<(u32, u32), Sim3>,
    }

    impl Biased {
        fn preferred(&self, a: usize, b: usize, centre: &[f64; 3]) -> Sim3 {
            let c = Vector3::from(*centre);
            let to = Sim3 { translation: -c, ..Sim3::identity() };
            let back = Sim3 { translation: c, ..Sim3::identity() };
            let turned = back.compose(&self.bias[&(a as u32, b as u32)]).compose(&to);
            self.truth[b].compose(&self.truth[a].inverse()).compose(&turned)
        }
    }

    impl RenderCheck for Biased {
        fn score(&mut self, reference: &Scene, instance: &Scene, id: u32, x: &Sim3) -> Result<Option<RenderScore>> {
            let of = |s: &Scene| s.opacities[0] as usize;
            let (a, b) = (of(instance), of(reference));
            assert_eq!(a as u32, id);
            let c = instance.means[0].map(|v| v as f64);
            let preferred = self.preferred(a, b, &c);
            let (p, q) = (Vector3::from(x.apply(&c)), Vector3::from(preferred.apply(&c)));
            let err = x.rotation_error_deg(&preferred) + 100.0 * (p - q).norm();
            let psnr = 40.0 - err;
            Ok(Some(RenderScore { views: 1, iou: 1.0, psnr, pose_psnr: psnr }))
        }
    }

    #[test]
    fn synchronised_poses_are_closer_to_the_truth_than_the_registrations_alone() {
        // Six instances in a row, turned every way; instance k's Gaussians carry k as their
        // opacity (the mock check reads it); its registration cloud is four points.
        let n = 6;
        let mut rng = rand_pcg::Pcg64::new(7, 11);
        use rand::Rng;
        let mut random_turn = |deg: f64| {
            let axis = [rng.random::<f64>() - 0.5, rng.random::<f64>() - 0.5, rng.random::<f64>() - 0.5];
            turn(axis, deg)
        };
        let truth: Vec<Sim3> =
            (0..n).map(|k| Sim3 { translation: Vector3::new(k as f64, 0.0, 0.0), ..random_turn(40.0) }).collect();
        let mut bias = std::collections::HashMap::new();
        for a in 0..n as u32 {
            for b in 0..n as u32 {
                bias.insert((a, b), random_turn(3.0));
            }
        }
        let opaque: Vec<Vec<[f64; 3]>> = (0..n)
            .map(|k| {
                (0..4)
                    .map(|i| truth[k].apply(&[0.1 * (i & 1) as f64, 0.1 * (i >> 1) as f64, 0.05 * i as f64]))
                    .collect()
            })
            .collect();
        let parts: Vec<Scene> = (0..n)
            .map(|k| {
                let c = centroid(&opaque[k]);
                Scene {
                    sh_degree: 0,
                    means: vec![[c.x as f32, c.y as f32, c.z as f32]; 4],
                    scales: vec![[0.0; 3]; 4],
                    quats: vec![[1.0, 0.0, 0.0, 0.0]; 4],
                    opacities: vec![k as f32; 4],
                    sh: vec![0.0; 12],
                }
            })
            .collect();
        let mut rc = Biased { truth: truth.clone(), bias };
        let r = 0;
        let ids: Vec<u32> = (0..n as u32).collect();
        // The registrations onto the reference alone: each lands on its pair's preferred pose.
        let relative: Vec<Option<Sim3>> = (0..n)
            .map(|k| {
                let c = parts[k].means[0].map(|v| v as f64);
                Some(if k == r { Sim3::identity() } else { rc.preferred(k, r, &c) })
            })
            .collect();
        let synced = synchronise(&mut rc, &parts, &opaque, &ids, r, &relative, true).unwrap();
        assert!(synced[r].is_none());
        let (mut before, mut after) = (0.0, 0.0);
        for k in 1..n {
            let t = truth[r].compose(&truth[k].inverse());
            let s = synced[k].expect("synchronised");
            before += relative[k].unwrap().rotation_error_deg(&t);
            after += s.pose.rotation_error_deg(&t);
            assert!(s.spread_deg > 0.0 && s.moved_deg > 0.0, "{s:?}");
        }
        // Measured: 1.49° against 3.00°.
        assert!(after < 0.6 * before, "mean error {:.2}° synchronised, {:.2}° alone", after / 5.0, before / 5.0);
    }

    #[test]
    fn two_accepted_instances_besides_the_reference_are_left_alone() {
        struct Never;
        impl RenderCheck for Never {
            fn score(&mut self, _: &Scene, _: &Scene, _: u32, _: &Sim3) -> Result<Option<RenderScore>> {
                panic!("no pair to register")
            }
        }
        let parts = vec![Scene::default(); 4];
        let opaque = vec![vec![[0.0; 3]]; 4];
        let relative = vec![Some(Sim3::identity()), Some(Sim3::identity()), None, Some(Sim3::identity())];
        let out = synchronise(&mut Never, &parts, &opaque, &[1, 2, 3, 4], 0, &relative, true).unwrap();
        assert!(out.iter().all(|s| s.is_none()));
    }
}
