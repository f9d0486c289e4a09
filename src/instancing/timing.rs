//! Where the instance stage spends its time: wall seconds per step and the work counted
//! (registrations, render checks), written to `instance.json` and the report. [`Timed`] wraps
//! a [`RenderCheck`] to count its calls and time; each step's own time is its wall time less
//! the render checks inside it.
use std::cell::Cell;
use std::time::Instant;

use anyhow::Result;
use serde::Serialize;

use crate::instancing::pose::{Detail, RenderCheck, RenderScore};
use crate::model::scene::Scene;
use crate::register::Sim3;

/// The instance stage's steps (seconds, wall clock) and its work.
#[derive(Clone, Debug, Default, Serialize)]
pub struct StepTimes {
    /// The scene's up axis, each instance's size signature and the pose graph's edges.
    pub candidates_s: f64,
    /// Registrations onto the reference (features, RANSAC, ICP, geometric checks), their
    /// render checks excluded.
    pub registration_s: f64,
    /// The pose graph: the edges' registrations and the synchronisation, render checks excluded.
    pub synchronisation_s: f64,
    /// Every render check ([`RenderCheck::score`]), wherever it ran.
    pub render_checks_s: f64,
    /// Templates and offsets.
    pub templates_s: f64,
    /// The background budget and the rebalance (the pipeline's compaction; 0 without).
    pub compaction_s: f64,
    /// Registrations run (a RANSAC search of one instance onto another, per seed).
    pub registrations: usize,
    /// Edges of the pose graphs registered (refined against the images from the pose their
    /// registrations onto the reference imply).
    pub edges: usize,
    /// Render checks run (each renders the instance's chosen views once).
    pub render_checks: usize,
}

impl StepTimes {
    pub fn total_s(&self) -> f64 {
        self.candidates_s
            + self.registration_s
            + self.synchronisation_s
            + self.render_checks_s
            + self.templates_s
            + self.compaction_s
    }

    /// One line: "instance stage: 512 s (registration 80 s, …); 45 registrations, …".
    pub fn line(&self) -> String {
        format!(
            "instance stage {:.0} s: candidates {:.1} s, registration {:.1} s, synchronisation {:.1} s, render checks {:.1} s, templates {:.1} s, compaction {:.1} s; {} registrations, {} graph edges, {} render checks",
            self.total_s(),
            self.candidates_s,
            self.registration_s,
            self.synchronisation_s,
            self.render_checks_s,
            self.templates_s,
            self.compaction_s,
            self.registrations,
            self.edges,
            self.render_checks
        )
    }
}

/// The render checks' calls and seconds so far, shared by a [`Timed`] check and the steps
/// that read it.
#[derive(Debug, Default)]
pub struct Clock {
    seconds: Cell<f64>,
    calls: Cell<usize>,
}

impl Clock {
    pub fn seconds(&self) -> f64 {
        self.seconds.get()
    }

    pub fn calls(&self) -> usize {
        self.calls.get()
    }
}

/// A [`RenderCheck`] that counts its calls and adds up their time on a [`Clock`].
pub struct Timed<'a> {
    inner: &'a mut dyn RenderCheck,
    clock: &'a Clock,
}

impl<'a> Timed<'a> {
    pub fn new(inner: &'a mut dyn RenderCheck, clock: &'a Clock) -> Timed<'a> {
        Timed { inner, clock }
    }
}

impl RenderCheck for Timed<'_> {
    fn score_at(
        &mut self,
        reference: &Scene,
        instance: &Scene,
        id: u32,
        x: &Sim3,
        detail: Detail,
    ) -> Result<Option<RenderScore>> {
        let t = Instant::now();
        let s = self.inner.score_at(reference, instance, id, x, detail);
        self.clock.seconds.set(self.clock.seconds.get() + t.elapsed().as_secs_f64());
        self.clock.calls.set(self.clock.calls.get() + 1);
        s
    }
}

/// Times one step: its wall seconds less the render-check seconds on the [`Clock`] meanwhile.
pub struct Step {
    start: Instant,
    checks_before: f64,
}

impl Step {
    pub fn start(clock: &Clock) -> Step {
        Step { start: Instant::now(), checks_before: clock.seconds() }
    }

    /// Seconds of the step's own work so far.
    pub fn own(&self, clock: &Clock) -> f64 {
        (self.start.elapsed().as_secs_f64() - (clock.seconds() - self.checks_before)).max(0.0)
    }
}
