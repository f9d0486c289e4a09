//! A group's pose graph ([`crate::instancing::synchronise`]): its edges registered against the
//! images, its poses synchronised, each synchronised pose checked before it is kept, and what
//! was decided ([`GraphReport`]).
use anyhow::Result;

use super::{refine_pose, Detail, InstanceReport, PoseCheck, RenderCheck, MAX_EVALUATIONS};
use crate::instancing::options::{InstanceOptions, Status};
use crate::instancing::synchronise::{candidate_edges, size_signature, synchronise};
use crate::model::scene::Scene;
use crate::register::{centroid, object_size, RegisterOptions, Sim3};

/// Seconds between the progress lines of a long step (the group's synchronisation).
const PROGRESS_SECONDS: f64 = 10.0;

/// A group's pose graph as `synchronise_group` decided it (instance ids, not indices).
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct GraphReport {
    pub group: String,
    /// Edges registered besides the registrations onto the reference.
    pub edges: usize,
    /// Cycles (an edge with the two registrations onto the reference) checked, and those that
    /// did not close ([`crate::instancing::synchronise::Cycle::closes`]).
    pub cycles: usize,
    pub open_cycles: Vec<GraphCycle>,
    /// Registrations refused: (from id, to id, rotation °, translation as a fraction of size).
    pub refused: Vec<GraphCycle>,
}

/// A cycle or registration of the graph, by instance ids.
#[derive(Clone, Debug, serde::Serialize)]
pub struct GraphCycle {
    pub from: u32,
    pub to: u32,
    pub rotation_deg: f64,
    pub translation_fraction: f64,
}

/// [`synchronise`]s the accepted poses of a group over its pose graph
/// ([`candidate_edges`]: `o.neighbours` per instance by [`size_signature`]) and keeps each
/// synchronised pose that still passes every check (both fitnesses, scale, the render check
/// against the reference); one that fails keeps its registration onto the reference alone,
/// unless the graph refused that registration (its cycles did not close): then the instance is
/// refused. Reports say which.
#[allow(clippy::too_many_arguments)]
pub(crate) fn synchronise_group(
    rc: &mut dyn RenderCheck,
    parts: &[Scene],
    opaque: &[Vec<[f64; 3]>],
    ids: &[u32],
    r: usize,
    relative: &mut [Option<Sim3>],
    reg: &RegisterOptions,
    o: &InstanceOptions,
    reports: &mut [InstanceReport],
    progress: &mut impl FnMut(&str),
) -> Result<GraphReport> {
    let rigid = !o.with_scale;
    let accepted: Vec<usize> = (0..relative.len()).filter(|&k| k != r && relative[k].is_some()).collect();
    let signatures: Vec<Vec<f64>> = opaque.iter().map(|p| size_signature(p)).collect();
    let edges = candidate_edges(&signatures, &accepted, r, o.neighbours);
    let size = object_size(&opaque[r]);
    // An edge a → b: refined against a's views from the pose the registrations imply, steps
    // from 0.5° (each registration was refined to 0.25°: their composition is within a degree
    // or two, which the search walks in repeated steps). Edges take seconds each on a CPU
    // device: a line every PROGRESS_SECONDS.
    let (mut done, mut last) = (0, std::time::Instant::now());
    let total = edges.len();
    let graph = synchronise(opaque, r, relative, &edges, size, |a, b, start| {
        done += 1;
        if last.elapsed().as_secs_f64() >= PROGRESS_SECONDS {
            progress(&format!("synchronising the group's poses: edge {done} of {total}"));
            last = std::time::Instant::now();
        }
        let Some(score) = rc.score_at(&parts[b], &parts[a], ids[a], &start, Detail::Coarse)? else { return Ok(None) };
        let (centre, size) = (centroid(&opaque[b]), object_size(&opaque[b]));
        let search = (2..4, MAX_EVALUATIONS);
        let start = (start, score, Detail::Coarse);
        Ok(Some(refine_pose(rc, &parts[b], &parts[a], ids[a], start, centre, size, rigid, search)?.0))
    })?;
    let by_id = |from: usize, to: usize, rotation_deg: f64, translation_fraction: f64| GraphCycle {
        from: ids[from],
        to: ids[to],
        rotation_deg,
        translation_fraction,
    };
    let out = GraphReport {
        group: reports.first().map(|x| x.group.clone()).unwrap_or_default(),
        edges: graph.edges,
        cycles: graph.cycles.len(),
        open_cycles: graph
            .cycles
            .iter()
            .filter(|c| !c.closes())
            .map(|c| by_id(c.a, c.b, c.rotation_deg, c.translation_fraction))
            .collect(),
        refused: graph.refused.iter().map(|e| by_id(e.from, e.to, e.rotation_deg, e.translation_fraction)).collect(),
    };
    for e in &graph.refused {
        progress(&format!(
            "{}: the registration {} → {} is refused: it disagrees with the group's other registrations by {:.1}° / {:.1} % of the size (a cycle through it does not close)",
            out.group,
            ids[e.from],
            ids[e.to],
            e.rotation_deg,
            100.0 * e.translation_fraction
        ));
    }
    for &k in &accepted {
        let outvoted = graph.refused.iter().find(|e| e.from == k && e.to == r);
        let failure = match &graph.poses[k] {
            None => Some("no registration of the graph is left to place it".to_string()),
            Some(s) => {
                let check = PoseCheck::measure(&opaque[k], &opaque[r], &s.pose, reg.voxel);
                let score = rc.score(&parts[r], &parts[k], ids[k], &s.pose)?;
                let failure = check.failure(&s.pose, &o.accept, rigid).or_else(|| match score {
                    Some(score) => score.failure(&o.accept),
                    None => Some("the instance shows in no training view".into()),
                });
                if failure.is_none() {
                    relative[k] = Some(s.pose);
                    let report = &mut reports[k];
                    report.relative = s.pose;
                    report.check = check;
                    report.render = score;
                    report.synchronised = Some(*s);
                    progress(&format!(
                        "{}: synchronised over {} registrations (moved {:.2}°, estimates within {:.2}°)",
                        ids[k], s.estimates, s.moved_deg, s.spread_deg
                    ));
                }
                failure
            }
        };
        match (failure, outvoted) {
            (None, _) => {}
            (Some(why), None) => progress(&format!(
                "{}: synchronised pose fails a check ({why}); the registration onto {} is kept",
                ids[k], ids[r]
            )),
            (Some(why), Some(e)) => {
                let why = format!(
                    "its registration onto {} disagrees with its cycles by {:.1}° / {:.1} % of the size, and the pose through its neighbours fails: {why}",
                    ids[r],
                    e.rotation_deg,
                    100.0 * e.translation_fraction
                );
                progress(&format!("{}: refused, stays plain: {why}", ids[k]));
                relative[k] = None;
                reports[k].status = Status::Refused(why);
            }
        }
    }
    Ok(out)
}
