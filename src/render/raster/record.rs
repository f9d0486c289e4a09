//! The recording of one frame's forward passes into the rasterizer's command buffer (replayed
//! for every frame until the scene, image size or intersection capacity changes).
use anyhow::Result;

use super::*;
use crate::gpu::kernels::Kernels;
use crate::gpu::kernels::{bits_for, record_scan, record_sort, Counts, Scan, SortBuffers};
use crate::gpu::{Buffer, Recorder};

impl Rasterizer {
    pub(super) fn record(&mut self, scene: &GpuScene, fp: &FrameParams, readback: bool) -> Result<()> {
        let pass = Passes {
            k: &self.k,
            scene,
            g: self.gauss.as_ref().unwrap(),
            is: self.isect.as_ref().unwrap(),
            im: self.image.as_ref().unwrap(),
            c: &self.counts,
            frame: &self.frame_ub,
            readback_counts: &self.readback_counts,
            readback,
        };
        let select = scene.inst.select.map(|a| (a, self.select.as_ref().unwrap()));
        let placeholder = &self.placeholder;
        let poison = self.poison;
        let quads = self.quads.as_ref().filter(|_| self.forward == Forward::Quads);
        let mut depth_result = 0;
        let mut isect_result = 0;
        self.cmd.record_timed(self.timer.as_mut(), |rec| {
            pass.setup(rec, poison)?;
            if let Some((args, sel)) = select {
                pass.select(rec, &args, sel, poison)?;
            }
            let (inst_offsets, inst_level) =
                select.map_or((placeholder, placeholder), |(_, s)| (&s.inst_offsets, &s.inst_level));
            depth_result = pass.project(rec, inst_offsets, inst_level)?;
            let depth_ids = &pass.g.depth_ids[depth_result];
            if let Some(q) = quads {
                q.record(
                    rec,
                    pass.k,
                    &pass.c.counts,
                    pass.frame,
                    [
                        ("depth_ids", depth_ids),
                        ("xys", &pass.g.xys),
                        ("conics", &pass.g.conics),
                        ("colours", &pass.g.colours),
                    ],
                    &pass.im.out_image,
                )?;
                rec.end_pass("draw")?;
            } else {
                isect_result = pass.rasterize(rec, depth_ids, fp)?;
            }
            pass.readback(rec)
        })?;
        self.depth_result = depth_result;
        self.isect_result = isect_result;
        Ok(())
    }
}

/// One frame's buffers, for the passes recorded in order: setup, (instance selection), project
/// (preprocess, compaction, depth sort), rasterize (intersections, tile sort, ranges, blend) or
/// the quads' draw, readback.
struct Passes<'a> {
    k: &'a Kernels,
    scene: &'a GpuScene,
    g: &'a GaussBufs,
    is: &'a IsectBufs,
    im: &'a ImageBufs,
    c: &'a Counts,
    frame: &'a Buffer,
    readback_counts: &'a Buffer,
    readback: bool,
}

impl Passes<'_> {
    /// Poisons the per-frame buffers when asked, sets the counts and clears the tile ranges.
    fn setup(&self, rec: &mut Recorder, poison: bool) -> Result<()> {
        let (g, is, im, c) = (self.g, self.is, self.im, self.c);
        if poison {
            for b in g
                .per_splat()
                .into_iter()
                .chain(&g.depth_keys)
                .chain(&g.depth_ids)
                .chain(&is.keys)
                .chain(&is.ids)
                .chain([&is.block_sums, &im.out_image, &im.last])
            {
                rec.fill(b, POISON);
            }
        }
        let mut init = [0u32; COUNT_SLOTS as usize];
        init[COUNT_GAUSSIANS as usize] = self.scene.len as u32;
        init[COUNT_INSTANCES as usize] = self.scene.inst.instances as u32;
        rec.update(&c.counts, &init);
        rec.fill(&im.ranges, 0);
        rec.fill(&im.tile_costs, 0);
        c.record_args(rec, self.k, COUNT_GAUSSIANS)?;
        rec.end_pass("setup")
    }

    /// The instances this frame draws and at which level, and the frame's splats: background +
    /// the selected instances' Gaussians, clamped to the per-splat buffers (the host grows them
    /// when more were needed).
    fn select<P: bytemuck::Pod>(&self, rec: &mut Recorder, args: &P, sel: &SelectBufs, poison: bool) -> Result<()> {
        let (k, c, scene) = (self.k, self.c, self.scene);
        if poison {
            for b in [&sel.inst_count, &sel.inst_level, &sel.inst_offsets, &sel.block_sums] {
                rec.fill(b, POISON);
            }
        }
        c.record_args(rec, k, COUNT_INSTANCES)?;
        rec.dispatch(
            &k.instance_select,
            &[
                ("frame_texels", self.frame),
                ("groups", &scene.inst.groups),
                ("xforms", &scene.inst.xforms),
                ("inst_count", &sel.inst_count),
                ("inst_level", &sel.inst_level),
            ],
            args,
            [(scene.inst.instances as u32).div_ceil(WG_SIZE).min(MAX_GROUPS), 1, 1],
        )?;
        record_scan(
            rec,
            k,
            c,
            &Scan {
                count_slot: COUNT_INSTANCES,
                mode: SCAN_MODE_VALUE,
                input: &sel.inst_count,
                gather: None,
                block_sums: &sel.block_sums,
                output: &sel.inst_offsets,
                out_slot: COUNT_SPLATS_NEEDED,
                clamp_slot: COUNT_GAUSSIANS,
                capacity: self.g.n as u32,
                out_bias: scene.num_background as u32,
            },
        )?;
        c.record_args(rec, k, COUNT_GAUSSIANS)?;
        rec.end_pass("select")
    }

    /// Preprocess (projection, SH colour, tiles touched), compaction of the visible splats and
    /// their depth sort; returns which of the two depth-id buffers holds the sorted ids.
    fn project(&self, rec: &mut Recorder, inst_offsets: &Buffer, inst_level: &Buffer) -> Result<usize> {
        let (k, c, g, scene) = (self.k, self.c, self.g, self.scene);
        let bindings: Vec<(&str, &Buffer)> = [
            ("frame_texels", self.frame),
            ("means", &scene.means),
            ("scales", &scene.scales),
            ("quats", &scene.quats),
            ("opacities", &scene.opacities),
            ("sh", &scene.sh),
            ("xys", &g.xys),
            ("conics", &g.conics),
            ("colours", &g.colours),
            ("depths", &g.depths),
            ("radii", &g.radii),
            ("tiles_touched", &g.tiles_touched),
        ]
        .into_iter()
        .chain(scene.instancing_bindings())
        .chain([("counts", &c.counts), ("inst_offsets", inst_offsets), ("inst_level", inst_level)])
        .collect();
        let items = Counts::args_offset(COUNT_GAUSSIANS, ARGS_ITEMS);
        rec.dispatch_indirect(&k.preprocess, &bindings, &(), &c.indirect, items)?;
        rec.end_pass("preprocess")?;
        record_scan(
            rec,
            k,
            c,
            &Scan {
                count_slot: COUNT_GAUSSIANS,
                mode: SCAN_MODE_NONZERO,
                input: &g.tiles_touched,
                gather: None,
                block_sums: &self.is.block_sums,
                output: &g.vis_offsets,
                out_slot: COUNT_VISIBLE,
                clamp_slot: NO_SLOT,
                capacity: 0,
                out_bias: 0,
            },
        )?;
        rec.dispatch_indirect(
            &k.compact,
            &[
                ("counts", &c.counts),
                ("tiles_touched", &g.tiles_touched),
                ("vis_offsets", &g.vis_offsets),
                ("depths", &g.depths),
                ("depth_keys", &g.depth_keys[0]),
                ("depth_ids", &g.depth_ids[0]),
            ],
            &(),
            &c.indirect,
            items,
        )?;
        c.record_args(rec, k, COUNT_VISIBLE)?;
        rec.end_pass("scan")?;
        // Depths are positive floats: the sign bit is 0, so 31 bits order them.
        let depth_bufs = SortBuffers {
            keys: [&g.depth_keys[0], &g.depth_keys[1]],
            vals: [&g.depth_ids[0], &g.depth_ids[1]],
            hist: &self.is.hist,
        };
        let depth_result = record_sort(rec, k, c, COUNT_VISIBLE, 31, &depth_bufs)?;
        rec.end_pass("depth_sort")?;
        Ok(depth_result)
    }

    /// The tile intersections of the depth-sorted splats, their tile sort, each tile's range and
    /// the blend; returns which of the two intersection-id buffers holds the sorted ids.
    fn rasterize(&self, rec: &mut Recorder, depth_ids: &Buffer, fp: &FrameParams) -> Result<usize> {
        let (k, c, g, is, im) = (self.k, self.c, self.g, self.is, self.im);
        record_scan(
            rec,
            k,
            c,
            &Scan {
                count_slot: COUNT_VISIBLE,
                mode: SCAN_MODE_GATHER,
                input: &g.tiles_touched,
                gather: Some(depth_ids),
                block_sums: &is.block_sums,
                output: &g.isect_offsets,
                out_slot: COUNT_ISECT_NEEDED,
                clamp_slot: COUNT_ISECT,
                capacity: is.cap as u32,
                out_bias: 0,
            },
        )?;
        rec.end_pass("scan")?;
        rec.dispatch_indirect(
            &k.emit,
            &[
                ("frame_texels", self.frame),
                ("counts", &c.counts),
                ("depth_ids", depth_ids),
                ("isect_offsets", &g.isect_offsets),
                ("xys", &g.xys),
                ("radii", &g.radii),
                ("isect_keys", &is.keys[0]),
                ("isect_ids", &is.ids[0]),
                ("conics", &g.conics),
                ("tile_costs", &im.tile_costs),
            ],
            &(),
            &c.indirect,
            Counts::args_offset(COUNT_VISIBLE, ARGS_ITEMS),
        )?;
        c.record_args(rec, k, COUNT_ISECT)?;
        rec.end_pass("emit")?;
        let tile_bufs =
            SortBuffers { keys: [&is.keys[0], &is.keys[1]], vals: [&is.ids[0], &is.ids[1]], hist: &is.hist };
        let isect_result = record_sort(rec, k, c, COUNT_ISECT, bits_for(fp.tiles_x * fp.tiles_y), &tile_bufs)?;
        rec.end_pass("tile_sort")?;
        rec.dispatch_indirect(
            &k.ranges,
            &[("counts", &c.counts), ("isect_keys", &is.keys[isect_result]), ("ranges", &im.ranges)],
            &(),
            &c.indirect,
            Counts::args_offset(COUNT_ISECT, ARGS_ITEMS),
        )?;
        rec.end_pass("ranges")?;
        for blend in &k.blend {
            rec.dispatch(
                blend,
                &[
                    ("frame_texels", self.frame),
                    ("ranges", &im.ranges),
                    ("isect_ids", &is.ids[isect_result]),
                    ("xys", &g.xys),
                    ("conics", &g.conics),
                    ("colours", &g.colours),
                    ("out_image", &im.out_image),
                    ("last", &im.last),
                    ("tile_costs", &im.tile_costs),
                ],
                &(),
                [fp.tiles_x, fp.tiles_y, 1],
            )?;
        }
        rec.end_pass("blend")?;
        Ok(isect_result)
    }

    /// The image (when asked for) and the counts back to the host.
    fn readback(&self, rec: &mut Recorder) -> Result<()> {
        let (im, c) = (self.im, self.c);
        if self.readback {
            rec.copy(&im.out_image, im.readback_image.as_ref().unwrap(), im.out_image.size);
        }
        rec.copy(&c.counts, self.readback_counts, c.counts.size);
        rec.end_pass("readback")
    }
}
