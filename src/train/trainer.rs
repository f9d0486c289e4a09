//! The GPU side of one training iteration: forward, loss, backward and Adam on a scene that
//! stays on the device, and the state read back at densification steps and checkpoints.
use std::sync::Arc;

use anyhow::Result;

use crate::dataset::View;
use crate::gpu::kernels::Kernels;
use crate::gpu::{CommandBuffer, Gpu};
use crate::model::instanced::{xform_from_params, xform_param_grads, Offsets, Similarity};
use crate::render::appearance::AppearanceBufs;
use crate::render::raster::backward::Grads;
use crate::render::raster::Rasterizer;
use crate::render::upload::GpuScene;
use crate::train::config::Config;
use crate::train::optim::{
    offset_buffers, param_buffers, record_adam, record_loss, AdamState, LearningRates, LossBufs,
};

use crate::train::state::*;

/// Losses and PSNR of one training iteration.
#[derive(Clone, Copy, Debug, Default)]
pub struct StepStats {
    pub loss: f64,
    pub l1: f64,
    pub ssim: f64,
    pub psnr: f64,
}

/// The GPU side of training: scene, gradients, Adam moments, rasterizer and loss buffers.
pub struct Trainer {
    gpu: Arc<Gpu>,
    k: Arc<Kernels>,
    pub scene: GpuScene,
    /// The instanced run's groups (None: plain).
    layout: Option<Layout>,
    /// Instance-transform parameters and Adam moments (host side; refined when `refine`).
    xforms: [Vec<[f32; 8]>; 3],
    refine: bool,
    grads: Grads,
    adam: AdamState,
    pub raster: Rasterizer,
    /// Per image size: the loss buffers and, when the run learns colour transforms, theirs.
    losses: Vec<(LossBufs, Option<AppearanceBufs>)>,
    /// The training photos' colour transforms (host side; empty: none learned).
    appearance: AppearanceState,
    /// The training cameras' corrections (host side; empty: none refined).
    cameras: crate::train::cameras::CameraState,
    cmd: CommandBuffer,
    timer: Option<crate::gpu::Timer>,
    /// GPU milliseconds per pass of the last iteration (forward passes, loss, backward, Adam).
    pub passes: Vec<(String, f64)>,
}

impl Trainer {
    /// `refine`: optimise the instance transforms of an instanced state too.
    pub fn new(gpu: &Arc<Gpu>, k: &Arc<Kernels>, st: &TrainState, refine: bool) -> Result<Trainer> {
        let (scene, grads, adam) = Trainer::upload_state(gpu, st, refine)?;
        Ok(Trainer {
            gpu: gpu.clone(),
            k: k.clone(),
            scene,
            layout: st.layout.clone(),
            xforms: [st.xform_params.clone(), st.xform_exp_avg.clone(), st.xform_exp_avg_sq.clone()],
            refine,
            grads,
            adam,
            raster: Rasterizer::new(gpu, k)?,
            losses: Vec::new(),
            appearance: st.appearance.clone(),
            cameras: st.cameras.clone(),
            cmd: CommandBuffer::new(gpu)?,
            timer: crate::gpu::Timer::new(gpu, 32)?,
            passes: Vec::new(),
        })
    }

    fn upload_state(gpu: &Arc<Gpu>, st: &TrainState, refine: bool) -> Result<(GpuScene, Grads, AdamState)> {
        let mut scene = match st.to_instanced()? {
            Some(inst) => {
                let mut s = GpuScene::instanced(gpu, &inst)?;
                s.inst.xform_grads = refine;
                if refine {
                    s.write_transforms(gpu, &st.xform_params.iter().map(xform_from_params).collect::<Vec<_>>())?;
                }
                s
            }
            None => GpuScene::new(gpu, &st.scene)?,
        };
        scene.active_sh_degree = st.active_sh_degree;
        scene.camera_grads = !st.cameras.is_empty();
        let grads = Grads::new(gpu, &scene)?;
        let adam = AdamState::new(gpu, &scene)?;
        for k in 0..5 {
            gpu.write(&adam.exp_avg[k], &st.exp_avg[k])?;
            gpu.write(&adam.exp_avg_sq[k], &st.exp_avg_sq[k])?;
        }
        for k in 0..3 {
            gpu.write(&adam.offset_exp_avg[k], &st.offset_exp_avg[k])?;
            gpu.write(&adam.offset_exp_avg_sq[k], &st.offset_exp_avg_sq[k])?;
        }
        if st.layout.is_some() {
            gpu.submit_and_wait(|rec| {
                grads.record_reset_stats(rec);
                Ok(())
            })?;
        } else {
            gpu.write(&grads.grad2d_accum, &st.grad2d_accum)?;
            gpu.write(&grads.grad2d_count, &st.grad2d_count)?;
            gpu.write(&grads.max_radii, &st.max_radii)?;
        }
        Ok((scene, grads, adam))
    }

    /// Replaces the device state (after densification or on resume).
    pub fn load(&mut self, st: &TrainState) -> Result<()> {
        let (scene, grads, adam) = Trainer::upload_state(&self.gpu, st, self.refine)?;
        self.scene = scene;
        self.layout = st.layout.clone();
        self.xforms = [st.xform_params.clone(), st.xform_exp_avg.clone(), st.xform_exp_avg_sq.clone()];
        self.appearance = st.appearance.clone();
        self.cameras = st.cameras.clone();
        self.grads = grads;
        self.adam = adam;
        Ok(())
    }

    /// Reads the whole device state back.
    pub fn download(&self, iteration: u64) -> Result<TrainState> {
        let g = &self.gpu;
        let n = self.scene.rows;
        let st = strides(self.scene.sh_degree);
        let read = |b: &crate::gpu::Buffer, len: usize| g.read::<f32>(b, len);
        let p = param_buffers(&self.scene);
        let params: Vec<Vec<f32>> = (0..5).map(|k| read(p[k], n * st[k])).collect::<Result<_>>()?;
        let m: Vec<Vec<f32>> = (0..5).map(|k| read(&self.adam.exp_avg[k], n * st[k])).collect::<Result<_>>()?;
        let v: Vec<Vec<f32>> = (0..5).map(|k| read(&self.adam.exp_avg_sq[k], n * st[k])).collect::<Result<_>>()?;
        let to5 = |v: Vec<Vec<f32>>| -> [Vec<f32>; 5] { v.try_into().unwrap() };
        let plain = self.layout.is_none();
        let stats = if plain { n } else { 0 };
        let pairs = self.scene.inst.pairs;
        let ow = [3, 3, 1];
        let ob = offset_buffers(&self.scene);
        let off: Vec<Vec<f32>> = (0..3).map(|k| read(ob[k], pairs * ow[k])).collect::<Result<_>>()?;
        let om: Vec<Vec<f32>> =
            (0..3).map(|k| read(&self.adam.offset_exp_avg[k], pairs * ow[k])).collect::<Result<_>>()?;
        let ov: Vec<Vec<f32>> =
            (0..3).map(|k| read(&self.adam.offset_exp_avg_sq[k], pairs * ow[k])).collect::<Result<_>>()?;
        let to3 = |v: Vec<Vec<f32>>| -> [Vec<f32>; 3] { v.try_into().unwrap() };
        let [dm, dc, dop] = to3(off);
        Ok(TrainState {
            iteration,
            active_sh_degree: self.scene.active_sh_degree,
            scene: scene_from_params(to5(params), self.scene.sh_degree),
            exp_avg: to5(m),
            exp_avg_sq: to5(v),
            grad2d_accum: read(&self.grads.grad2d_accum, stats)?,
            grad2d_count: g.read(&self.grads.grad2d_count, stats)?,
            max_radii: g.read(&self.grads.max_radii, stats)?,
            layout: self.layout.as_ref().map(|l| {
                // Refined transforms: the layout's matrices follow the parameters.
                let mut l = l.clone();
                if self.refine {
                    let mut it = self.xforms[0].iter();
                    for g in &mut l.groups {
                        for inst in &mut g.instances {
                            let x = xform_from_params(it.next().expect("one parameter set per instance"));
                            inst.1 = crate::model::instanced::mat4_to_rows(x.to_mat4());
                        }
                    }
                }
                l
            }),
            xform_params: self.xforms[0].clone(),
            xform_exp_avg: self.xforms[1].clone(),
            xform_exp_avg_sq: self.xforms[2].clone(),
            offsets: Offsets {
                d_means: bytemuck::pod_collect_to_vec(&dm),
                d_sh0: bytemuck::pod_collect_to_vec(&dc),
                d_opacities: dop,
            },
            offset_exp_avg: to3(om),
            offset_exp_avg_sq: to3(ov),
            appearance: self.appearance.clone(),
            cameras: self.cameras.clone(),
        })
    }

    /// The lens's vignetting as learned so far (none when the run learns no appearance).
    pub fn vignetting(&self) -> crate::render::appearance::Vignetting {
        self.appearance.vignetting
    }

    /// One iteration on training view `index` (`view`): forward, the view's colour transform
    /// when the run learns them, loss, backward and the Adam steps (`step` from 1).
    pub fn step(
        &mut self,
        view: &View,
        index: usize,
        cfg: &Config,
        lr: &LearningRates,
        step: u64,
    ) -> Result<StepStats> {
        let corrected = (!self.cameras.is_empty()).then(|| self.cameras.camera(index));
        let cam = corrected.as_ref().unwrap_or(&view.camera);
        self.raster.tile_cost_weight = cfg.tile_cost_weight;
        let frame = self.raster.render(&self.scene, cam, cfg.background)?;
        let colour = self.appearance.params.get(index).copied();
        let vignetting = self.appearance.vignetting;
        let li = match self.losses.iter().position(|l| l.0.width == cam.width && l.0.height == cam.height) {
            Some(i) => i,
            None => {
                let pixels = (cam.width * cam.height) as usize;
                let ab = colour.map(|_| AppearanceBufs::new(&self.gpu, pixels)).transpose()?;
                self.losses.push((LossBufs::new(&self.gpu, cam.width, cam.height)?, ab));
                self.losses.len() - 1
            }
        };
        // One submission: target upload, colour transform, loss, backward, Adam, sums back.
        self.losses[li].0.target_upload.write_mapped(&view.image)?;
        let (lb, ab) = (&self.losses[li].0, self.losses[li].1.as_ref());
        let image = self.raster.image_buffer().unwrap();
        let (k, scene, grads, adam, raster) = (&self.k, &self.scene, &self.grads, &self.adam, &self.raster);
        self.cmd.record_timed(self.timer.as_mut(), |rec| {
            lb.record_target_upload(rec)?;
            match (ab, &colour) {
                (Some(ab), Some(t)) => {
                    ab.record_apply(rec, k, image, t, &vignetting, cam)?;
                    record_loss(rec, k, &ab.adjusted, lb, cfg.ssim_weight)?;
                    ab.record_backward(rec, k, image, &lb.v_image, t, &vignetting, cam)?;
                    raster.record_backward(rec, scene, &ab.v_render, grads)?;
                }
                _ => {
                    record_loss(rec, k, image, lb, cfg.ssim_weight)?;
                    raster.record_backward(rec, scene, &lb.v_image, grads)?;
                }
            }
            record_adam(rec, k, scene, grads, adam, lr, step)?;
            lb.record_sums_readback(rec)
        })?;
        self.cmd.submit_and_wait()?;
        let sums: Vec<f32> = lb.sums_readback.read_mapped(crate::shared::LOSS_SLOTS as usize)?;
        let (l1, ssim) = lb.means(&sums);
        let psnr = match (ab, &colour) {
            (Some(ab), Some(t)) => {
                let g = ab.read_grads()?;
                self.appearance.step(index, &g, cfg.appearance.lr(step, cfg.lr.position_max_steps));
                let photo = crate::render::appearance::apply_photo(t, &vignetting, cam, &frame.image);
                crate::util::psnr(&photo, &view.image)
            }
            _ => crate::util::psnr(&frame.image, &view.image),
        };
        if self.refine && self.layout.is_some() {
            self.step_transforms(&cfg.lr, step)?;
        }
        if !self.cameras.is_empty() && lr.cameras.iter().any(|&r| r > 0.0) {
            let terms: Vec<f32> = self.gpu.read(&self.grads.v_camera, crate::shared::CAMERA_GRAD_TERMS as usize)?;
            self.cameras.step(index, &terms, lr.cameras);
        }
        self.passes = frame.passes.clone();
        if let Some(t) = &self.timer {
            self.passes.extend(t.results()?);
        }
        let w = cfg.ssim_weight as f64;
        Ok(StepStats { loss: (1.0 - w) * l1 + w * (1.0 - ssim), l1, ssim, psnr })
    }
}

impl Trainer {
    /// Adam on the instance transforms (host side, f64, the twin of `adam.comp`) at the
    /// `lr.transform_*` rates; then the new transforms go to the device.
    fn step_transforms(&mut self, cfg: &crate::train::config::LrConfig, step: u64) -> Result<()> {
        use crate::shared::XFORM_GRAD_TERMS;
        let n = self.xforms[0].len();
        let terms: Vec<f32> = self.gpu.read(&self.grads.v_xforms, n * XFORM_GRAD_TERMS as usize)?;
        for (i, chunk) in terms.chunks_exact(XFORM_GRAD_TERMS as usize).enumerate() {
            let g = xform_param_grads(&self.xforms[0][i], chunk);
            let f = |a: &[f32; 8]| a.map(f64::from);
            let (mut p, mut m, mut v) = (f(&self.xforms[0][i]), f(&self.xforms[1][i]), f(&self.xforms[2][i]));
            for (range, rate) in
                [(0..4, cfg.transform_rotation), (4..7, cfg.transform_translation), (7..8, cfg.transform_scale)]
            {
                let a = crate::render::reference::backward::AdamStep {
                    lr: rate as f64,
                    beta1: crate::train::optim::BETA1,
                    beta2: crate::train::optim::BETA2,
                    eps: crate::train::optim::EPS as f64,
                    step,
                };
                crate::render::reference::backward::adam(
                    &mut p[range.clone()],
                    &g[range.clone()],
                    &mut m[range.clone()],
                    &mut v[range],
                    a,
                );
            }
            self.xforms[0][i] = p.map(|x| x as f32);
            self.xforms[1][i] = m.map(|x| x as f32);
            self.xforms[2][i] = v.map(|x| x as f32);
        }
        let transforms: Vec<Similarity> = self.xforms[0].iter().map(xform_from_params).collect();
        self.scene.write_transforms(&self.gpu, &transforms)
    }
}
