//! The GPU radix sort on its own: key-value pairs in, stably sorted pairs out. Used by the
//! tests (against a CPU stable sort) and by the sort benchmark.
use std::sync::Arc;

use anyhow::{bail, Result};

use crate::gpu::kernels::{record_sort, sort_hist_for, Counts, Kernels, SortBuffers};
use crate::gpu::{Buffer, CommandBuffer, Gpu, Timer};
use crate::shared::COUNT_SORT;

pub struct GpuSort {
    gpu: Arc<Gpu>,
    k: Arc<Kernels>,
    counts: Counts,
    keys: [Buffer; 2],
    vals: [Buffer; 2],
    hist: Buffer,
    capacity: usize,
}

/// Result of one GPU sort.
pub struct Sorted {
    pub keys: Vec<u32>,
    pub vals: Vec<u32>,
    /// GPU time of the sort passes in milliseconds, when the device has timestamps.
    pub gpu_ms: Option<f64>,
}

impl GpuSort {
    pub fn new(gpu: &Arc<Gpu>, k: &Arc<Kernels>, capacity: usize) -> Result<GpuSort> {
        let bytes = capacity as u64 * 4;
        Ok(GpuSort {
            gpu: gpu.clone(),
            k: k.clone(),
            counts: Counts::new(gpu)?,
            keys: [gpu.storage("sort-keys-a", bytes)?, gpu.storage("sort-keys-b", bytes)?],
            vals: [gpu.storage("sort-vals-a", bytes)?, gpu.storage("sort-vals-b", bytes)?],
            hist: gpu.storage("sort-hist", sort_hist_for(k, capacity as u64) * 4)?,
            capacity,
        })
    }

    /// Sorts (keys, vals) stably by the low `bits` bits of the keys. Higher key bits must be 0.
    /// `repeats` > 1 re-runs the same sort (from the same input) and reports the median time.
    pub fn sort(&mut self, keys: &[u32], vals: &[u32], bits: u32, repeats: usize) -> Result<Sorted> {
        let n = keys.len();
        if n != vals.len() || n > self.capacity {
            bail!("sort of {n} keys with {} values, capacity {}", vals.len(), self.capacity);
        }
        let gpu = self.gpu.clone();
        let mut timer = Timer::new(&gpu, 4)?;
        let cmd = CommandBuffer::new(&gpu)?;
        let mut result = 0;
        let mut times = Vec::new();
        // Each repeat sorts a fresh copy, so the input pair 0 is restored first (untimed).
        let staging_keys = gpu.upload("sort-in-keys", keys)?;
        let staging_vals = gpu.upload("sort-in-vals", vals)?;
        cmd.record_timed(timer.as_mut(), |rec| {
            rec.copy(&staging_keys, &self.keys[0], (n * 4) as u64);
            rec.copy(&staging_vals, &self.vals[0], (n * 4) as u64);
            rec.update(&self.counts.counts, &[0u32, 0, 0, 0, n as u32]);
            self.counts.record_args(rec, &self.k, COUNT_SORT)?;
            rec.end_pass("setup")?;
            let bufs = SortBuffers {
                keys: [&self.keys[0], &self.keys[1]],
                vals: [&self.vals[0], &self.vals[1]],
                hist: &self.hist,
            };
            result = record_sort(rec, &self.k, &self.counts, COUNT_SORT, bits, &bufs)?;
            rec.end_pass("sort")
        })?;
        for _ in 0..repeats.max(1) {
            cmd.submit_and_wait()?;
            if let Some(t) = &timer {
                times.extend(t.results()?.into_iter().filter(|(n, _)| n == "sort").map(|p| p.1));
            }
        }
        times.sort_by(f64::total_cmp);
        Ok(Sorted {
            keys: gpu.read(&self.keys[result], n)?,
            vals: gpu.read(&self.vals[result], n)?,
            gpu_ms: times.get(times.len() / 2).copied(),
        })
    }
}
