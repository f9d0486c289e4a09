//! All compute kernels, built once per device, and the recording of the multi-dispatch
//! building blocks: indirect arguments, the reduce-then-scan prefix sum and the radix sort.
use std::sync::Arc;

use anyhow::Result;

use crate::gpu::{Buffer, Gpu, Kernel, Recorder};
use crate::shared::*;

pub struct Kernels {
    pub preprocess: Kernel,
    pub compact: Kernel,
    pub emit: Kernel,
    pub ranges: Kernel,
    /// For the tiles whose splats fit its row loops (emit's tile costs, see BLEND_LOOP_ITERATIONS),
    /// then the rest (specialization constant CROWDED_TILES 0 and 1); dispatch both, in any order.
    pub blend: [Kernel; 2],
    pub dispatch_args: Kernel,
    /// The draw path's indirect draw command (render::raster::quads).
    pub draw_args: Kernel,
    pub scan_reduce: Kernel,
    pub scan_blocks: Kernel,
    pub scan_down: Kernel,
    pub sort_count: Kernel,
    pub sort_scatter: Kernel,
    pub sort_small: Kernel,
    /// As `blend`: both dispatched.
    pub blend_backward: [Kernel; 2],
    /// Over every parameter row, then (plain scenes) over the frame's visible Gaussians only
    /// (specialization constant VISIBLE_ROWS 0 and 1), then the latter with the camera gradients
    /// (CAMERA_GRADS 1: training's camera refinement; a constant, so the other two skip its work).
    pub preprocess_backward: [Kernel; 3],
    pub xform_grad_reduce: Kernel,
    /// A plain frame's camera gradients (training's camera refinement).
    pub camera_grad_reduce: Kernel,
    pub loss_moments_h: Kernel,
    pub loss_ssim_v: Kernel,
    pub loss_cotangents_h: Kernel,
    pub loss_grad_v: Kernel,
    /// The per-photo colour transform and its backward (render::appearance).
    pub appearance: Kernel,
    pub appearance_backward: Kernel,
    pub adam: Kernel,
    pub adam_vec4: Kernel,
    pub seg_accumulate: Kernel,
    pub present: Kernel,
    pub instance_select: Kernel,
    pub policy: KernelPolicy,
    /// Threads per radix-sort workgroup (specialization constant 3 of the sort kernels).
    pub sort_wg: u32,
    /// Threads per `scan_reduce` / `scan_down` workgroup (their specialization constant 1).
    pub scan_wg: u32,
}

/// Device-dependent kernel choices (specialization constants).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct KernelPolicy {
    /// Keys per thread in a radix-sort block (SORT_ITEMS_CPU or SORT_ITEMS_GPU).
    pub sort_items: u32,
    /// Each thread's run of keys (sort) or items (scan) is its own column of the table that
    /// the one-workgroup `scan_blocks` scans: no shared memory and no barrier in `sort_count`,
    /// `sort_scatter`, `scan_reduce` and `scan_down`, workgroups of one subgroup, more columns
    /// to scan. Else a workgroup's block is a column.
    pub thread_runs: bool,
    /// Key bits per radix-sort pass (SORT_BITS_CPU or SORT_BITS_GPU; blocks take at most the
    /// latter).
    pub sort_bits: u32,
    /// Up to this many keys one workgroup sorts in one dispatch (`sort_small.comp`); 0: never.
    pub sort_small_max: u32,
    /// Pixels of a tile column each blend invocation owns (divides TILE_SIZE).
    pub blend_pixels_per_thread: u32,
    /// `blend` and `blend_backward` stage a tile's splats through shared memory in batches
    /// (else every invocation fetches each splat from the texel buffers itself: no shared
    /// memory, no barrier).
    pub blend_shared_batches: bool,
    /// `preprocess` and `emit` test the tiles of a splat larger than the subgroup with the whole
    /// subgroup (`glsl/tiles_subgroup.glsl`), else each splat's own invocation tests them.
    pub large_splats_by_subgroup: bool,
    /// Gradient kernels add floats with atomics (else a compare-and-swap loop).
    pub float_atomics: bool,
}

impl KernelPolicy {
    /// For GPUs: short sort runs for many workgroups; one pixel per blend invocation; a large
    /// splat's tiles tested by its whole subgroup. No one-dispatch sort: its threads' long
    /// serial runs suit a CPU, not a GPU.
    pub const GPU: KernelPolicy = KernelPolicy {
        sort_items: SORT_ITEMS_GPU,
        thread_runs: false,
        sort_bits: SORT_BITS_GPU,
        sort_small_max: 0,
        blend_pixels_per_thread: 1,
        blend_shared_batches: true,
        large_splats_by_subgroup: true,
        float_atomics: true,
    };
    /// For CPU devices (lavapipe): every workgroup with barriers has a large fixed cost
    /// (llvmpipe runs such workgroups as coroutines) and every load costs far more than
    /// arithmetic, so long sort runs that are their own histogram columns (no barrier), 8-bit
    /// digits (4 passes for a 31-bit depth key instead of 6), inputs up to SORT_SMALL_MAX_CPU
    /// keys sorted in one dispatch, a whole tile column per blend invocation that fetches
    /// every splat itself (a texel fetch is a vector gather on lavapipe, a shared-memory load a
    /// loop over the lanes), and each splat's tiles tested by its own invocation.
    pub const CPU: KernelPolicy = KernelPolicy {
        sort_items: SORT_ITEMS_CPU,
        thread_runs: true,
        sort_bits: SORT_BITS_CPU,
        sort_small_max: SORT_SMALL_MAX_CPU,
        blend_pixels_per_thread: TILE_SIZE,
        blend_shared_batches: false,
        large_splats_by_subgroup: false,
        float_atomics: true,
    };

    pub fn for_device(gpu: &Gpu) -> KernelPolicy {
        let p = if gpu.info.kind == "CPU" { KernelPolicy::CPU } else { KernelPolicy::GPU };
        KernelPolicy { float_atomics: gpu.info.float_atomics, ..p }
    }
}

impl Kernels {
    /// All kernels, specialised for the device.
    pub fn new(gpu: &Arc<Gpu>) -> Result<Arc<Kernels>> {
        Kernels::with_policy(gpu, KernelPolicy::for_device(gpu))
    }

    /// All kernels with an explicit policy (tests run both on any device).
    pub fn with_policy(gpu: &Arc<Gpu>, policy: KernelPolicy) -> Result<Arc<Kernels>> {
        if policy.float_atomics && !gpu.info.float_atomics {
            anyhow::bail!("device '{}' has no float32 buffer atomic add", gpu.info.name);
        }
        let k = |name: &str, spv: &[u8]| Kernel::new(gpu, name, spv);
        let atomics = |f: &'static [u8], cas: &'static [u8]| if policy.float_atomics { f } else { cas };
        // Thread runs need no shared memory or barrier, so a workgroup is one subgroup.
        let sort_wg = if policy.thread_runs { gpu.info.min_subgroup_size } else { SORT_WG };
        let scan_wg = if policy.thread_runs { gpu.info.min_subgroup_size } else { WG_SIZE };
        if !SCAN_BLOCK.is_multiple_of(scan_wg) {
            anyhow::bail!("subgroup size {scan_wg} does not divide the scan block {SCAN_BLOCK}");
        }
        let scan_spec = [scan_wg, policy.thread_runs as u32];
        if (!policy.thread_runs && policy.sort_bits > SORT_BITS_GPU) || policy.sort_bits == 0 {
            anyhow::bail!("sort policy: {} bits per pass does not fit the sort kernels", policy.sort_bits);
        }
        // lavapipe ends every loop of an invocation after 65 535 iterations of all its loops
        // together: the one-dispatch sort's thread walks its run twice per pass.
        let small_run = policy.sort_small_max.div_ceil(SORT_SMALL_WG);
        if 32u32.div_ceil(policy.sort_bits) * (2 * small_run + (5 << policy.sort_bits)) > 60_000 {
            anyhow::bail!("sort policy: {} keys are too many for the one-dispatch sort", policy.sort_small_max);
        }
        let sort_spec = [policy.sort_items, policy.thread_runs as u32, sort_wg, policy.sort_bits];
        let blend_spec = |crowded: u32| {
            [
                policy.blend_pixels_per_thread,
                TILE_SIZE / policy.blend_pixels_per_thread,
                crowded,
                policy.blend_shared_batches as u32,
            ]
        };
        Ok(Arc::new(Kernels {
            preprocess: Kernel::with_spec(
                gpu,
                "preprocess",
                spirv::PREPROCESS,
                &[policy.large_splats_by_subgroup as u32],
            )?,
            compact: k("compact", spirv::COMPACT)?,
            emit: Kernel::with_spec(
                gpu,
                "emit",
                spirv::EMIT,
                &[policy.blend_pixels_per_thread, policy.large_splats_by_subgroup as u32],
            )?,
            ranges: k("ranges", spirv::RANGES)?,
            blend: [
                Kernel::with_spec(gpu, "blend", spirv::BLEND, &blend_spec(0))?,
                Kernel::with_spec(gpu, "blend (crowded tiles)", spirv::BLEND, &blend_spec(1))?,
            ],
            dispatch_args: k("dispatch_args", spirv::DISPATCH_ARGS)?,
            draw_args: k("draw_args", spirv::DRAW_ARGS)?,
            scan_reduce: Kernel::with_spec(gpu, "scan_reduce", spirv::SCAN_REDUCE, &scan_spec)?,
            scan_blocks: k("scan_blocks", spirv::SCAN_BLOCKS)?,
            scan_down: Kernel::with_spec(gpu, "scan_down", spirv::SCAN_DOWN, &scan_spec)?,
            sort_count: Kernel::with_spec(gpu, "sort_count", spirv::SORT_COUNT, &sort_spec)?,
            sort_scatter: Kernel::with_spec(gpu, "sort_scatter", spirv::SORT_SCATTER, &sort_spec)?,
            sort_small: Kernel::with_spec(gpu, "sort_small", spirv::SORT_SMALL, &sort_spec)?,
            blend_backward: [
                Kernel::with_spec(
                    gpu,
                    "blend_backward",
                    atomics(spirv::BLEND_BACKWARD, spirv::BLEND_BACKWARD_CAS),
                    &blend_spec(0),
                )?,
                Kernel::with_spec(
                    gpu,
                    "blend_backward (crowded tiles)",
                    atomics(spirv::BLEND_BACKWARD, spirv::BLEND_BACKWARD_CAS),
                    &blend_spec(1),
                )?,
            ],
            preprocess_backward: [
                Kernel::with_spec(gpu, "preprocess_backward", spirv::PREPROCESS_BACKWARD, &[0, 0])?,
                Kernel::with_spec(gpu, "preprocess_backward (visible rows)", spirv::PREPROCESS_BACKWARD, &[1, 0])?,
                Kernel::with_spec(
                    gpu,
                    "preprocess_backward (visible rows, camera gradients)",
                    spirv::PREPROCESS_BACKWARD,
                    &[1, 1],
                )?,
            ],
            xform_grad_reduce: k("xform_grad_reduce", spirv::XFORM_GRAD_REDUCE)?,
            camera_grad_reduce: k("camera_grad_reduce", spirv::CAMERA_GRAD_REDUCE)?,
            loss_moments_h: k("loss_moments_h", spirv::LOSS_MOMENTS_H)?,
            loss_ssim_v: k("loss_ssim_v", atomics(spirv::LOSS_SSIM_V, spirv::LOSS_SSIM_V_CAS))?,
            loss_cotangents_h: k("loss_cotangents_h", spirv::LOSS_COTANGENTS_H)?,
            loss_grad_v: k("loss_grad_v", spirv::LOSS_GRAD_V)?,
            appearance: k("appearance", spirv::APPEARANCE)?,
            appearance_backward: k(
                "appearance_backward",
                atomics(spirv::APPEARANCE_BACKWARD, spirv::APPEARANCE_BACKWARD_CAS),
            )?,
            adam: k("adam", spirv::ADAM)?,
            adam_vec4: k("adam_vec4", spirv::ADAM_VEC4)?,
            seg_accumulate: k("seg_accumulate", spirv::SEG_ACCUMULATE)?,
            present: k("present", spirv::PRESENT)?,
            instance_select: k("instance_select", spirv::INSTANCE_SELECT)?,
            policy,
            sort_wg,
            scan_wg,
        }))
    }

    /// Keys per radix-sort block (one workgroup's keys).
    pub fn sort_block(&self) -> u32 {
        self.sort_wg * self.policy.sort_items
    }

    /// Items per column of the generic scan's block sums: a thread's run or a whole block.
    pub fn scan_column(&self) -> u32 {
        if self.policy.thread_runs {
            SCAN_BLOCK / self.scan_wg
        } else {
            SCAN_BLOCK
        }
    }

    /// Keys per column of the radix-sort histogram table: a thread's run or a whole block.
    pub fn sort_column(&self) -> u32 {
        if self.policy.thread_runs {
            self.policy.sort_items
        } else {
            self.sort_block()
        }
    }
}

/// The `counts` buffer and the indirect-argument buffer derived from it.
pub struct Counts {
    pub counts: Buffer,
    pub indirect: Buffer,
}

impl Counts {
    pub fn new(gpu: &Arc<Gpu>) -> Result<Counts> {
        Ok(Counts {
            counts: gpu.storage("counts", COUNT_SLOTS as u64 * 4)?,
            indirect: gpu.storage("indirect", (COUNT_SLOTS * ARGS_PER_SLOT * 3) as u64 * 4)?,
        })
    }

    /// Byte offset of the indirect command `kind` (ARGS_*) of count `slot`.
    pub fn args_offset(slot: u32, kind: u32) -> u64 {
        ((slot * ARGS_PER_SLOT + kind) * 3 * 4) as u64
    }

    /// Writes the indirect commands of `slot` from the GPU-side count.
    pub fn record_args(&self, rec: &mut Recorder, k: &Kernels, slot: u32) -> Result<()> {
        let push = DispatchArgs {
            count_slot: slot,
            sort_block: k.sort_block(),
            sort_small_max: k.policy.sort_small_max,
            ..Default::default()
        };
        rec.dispatch(&k.dispatch_args, &[("counts", &self.counts), ("indirect", &self.indirect)], &push, [1, 1, 1])
    }
}

/// Number of column sums a scan of `n` items needs.
pub fn scan_blocks_for(k: &Kernels, n: u64) -> u64 {
    n.div_ceil(k.scan_column() as u64).max(1)
}

/// Length of the radix-sort histogram table for `n` keys.
pub fn sort_hist_for(k: &Kernels, n: u64) -> u64 {
    n.div_ceil(k.sort_column() as u64).max(1) << k.policy.sort_bits
}

/// One scan: input, optional gather list, output and where its total goes.
pub struct Scan<'a> {
    pub count_slot: u32,
    pub mode: u32,
    pub input: &'a Buffer,
    pub gather: Option<&'a Buffer>,
    pub block_sums: &'a Buffer,
    pub output: &'a Buffer,
    pub out_slot: u32,
    pub clamp_slot: u32,
    pub capacity: u32,
    /// Added to the total written to `out_slot`.
    pub out_bias: u32,
}

/// Records an exclusive scan of `counts[count_slot]` items (reduce, scan of block sums, down
/// sweep). The indirect arguments of `count_slot` must be written already.
pub fn record_scan(rec: &mut Recorder, k: &Kernels, c: &Counts, s: &Scan) -> Result<()> {
    let args = ScanArgs {
        count_slot: s.count_slot,
        mode: s.mode,
        out_slot: s.out_slot,
        clamp_slot: s.clamp_slot,
        capacity: s.capacity,
        divisor: k.scan_column(),
        multiplier: 1,
        out_bias: s.out_bias,
    };
    let gather = s.gather.unwrap_or(s.input);
    let off = Counts::args_offset(s.count_slot, ARGS_SCAN_BLOCKS);
    rec.dispatch_indirect(
        &k.scan_reduce,
        &[("counts", &c.counts), ("scan_in", s.input), ("gather", gather), ("block_sums", s.block_sums)],
        &args,
        &c.indirect,
        off,
    )?;
    rec.dispatch(&k.scan_blocks, &[("counts", &c.counts), ("data", s.block_sums)], &args, [1, 1, 1])?;
    rec.dispatch_indirect(
        &k.scan_down,
        &[
            ("counts", &c.counts),
            ("scan_in", s.input),
            ("gather", gather),
            ("block_sums", s.block_sums),
            ("scan_out", s.output),
        ],
        &args,
        &c.indirect,
        off,
    )
}

/// The buffers of one radix sort: input in `keys[0]`/`vals[0]`, `keys[1]`/`vals[1]` for the
/// ping-pong, and the digit-major histogram table (`sort_hist_for` entries).
pub struct SortBuffers<'a> {
    pub keys: [&'a Buffer; 2],
    pub vals: [&'a Buffer; 2],
    pub hist: &'a Buffer,
}

/// Records a stable LSD radix sort of `counts[slot]` (key, value) pairs on the low `bits` key
/// bits. Returns the index (0 or 1) of the key/value pair holding the result. The indirect
/// arguments of `slot` must be written.
pub fn record_sort(
    rec: &mut Recorder,
    k: &Kernels,
    c: &Counts,
    slot: u32,
    bits: u32,
    b: &SortBuffers,
) -> Result<usize> {
    let SortBuffers { keys, vals, hist } = *b;
    // The fewest passes of at most the policy's bits, with the bits spread evenly over them.
    let passes = bits.div_ceil(k.policy.sort_bits);
    let off = Counts::args_offset(slot, ARGS_SORT_BLOCKS);
    // Small inputs: every pass in one dispatch (dispatch_args gives the passes below no
    // workgroups then, and this one none otherwise).
    rec.dispatch_indirect(
        &k.sort_small,
        &[("counts", &c.counts), ("keys_a", keys[0]), ("vals_a", vals[0]), ("keys_b", keys[1]), ("vals_b", vals[1])],
        &SortArgs { count_slot: slot, shift: 0, bits, _pad0: 0 },
        &c.indirect,
        Counts::args_offset(slot, ARGS_SORT_SMALL),
    )?;
    let mut shift = 0;
    for p in 0..passes {
        let (i, o) = ((p % 2) as usize, ((p + 1) % 2) as usize);
        let pass_bits = (bits - shift).div_ceil(passes - p);
        let push = SortArgs { count_slot: slot, shift, bits: pass_bits, _pad0: 0 };
        shift += pass_bits;
        rec.dispatch_indirect(
            &k.sort_count,
            &[("counts", &c.counts), ("keys_in", keys[i]), ("hist", hist)],
            &push,
            &c.indirect,
            off,
        )?;
        let scan = ScanArgs {
            count_slot: slot,
            out_slot: NO_SLOT,
            clamp_slot: NO_SLOT,
            divisor: k.sort_column(),
            multiplier: 1 << pass_bits,
            ..Default::default()
        };
        rec.dispatch_indirect(
            &k.scan_blocks,
            &[("counts", &c.counts), ("data", hist)],
            &scan,
            &c.indirect,
            Counts::args_offset(slot, ARGS_SORT_SCAN),
        )?;
        rec.dispatch_indirect(
            &k.sort_scatter,
            &[
                ("counts", &c.counts),
                ("keys_in", keys[i]),
                ("vals_in", vals[i]),
                ("hist", hist),
                ("keys_out", keys[o]),
                ("vals_out", vals[o]),
            ],
            &push,
            &c.indirect,
            off,
        )?;
    }
    Ok((passes % 2) as usize)
}

/// Bits needed to hold values 0..n-1 (at least 1).
pub fn bits_for(n: u32) -> u32 {
    (32 - n.saturating_sub(1).leading_zeros()).max(1)
}

/// The device (`--device`, `INSTGS_DEVICE`, else the best one) and every kernel on it.
pub fn open_device(device: Option<String>) -> Result<(Arc<Gpu>, Arc<Kernels>)> {
    let gpu = crate::gpu::Gpu::new(&crate::gpu::GpuOptions::from_env(device))?;
    let k = Kernels::new(&gpu)?;
    Ok((gpu, k))
}
