//! The checkpoint file (`checkpoint.bin`): the whole training state and its config, written
//! atomically and read back with every size checked.
use std::io::Write;
use std::path::{Path, PathBuf};

use anyhow::{anyhow, bail, Context, Result};

use crate::dataset::DatasetIdentity;
use crate::model::instanced::Offsets;
use crate::train::config::Config;

use crate::train::state::*;

const MAGIC: &[u8; 8] = b"INSTGSCK";
/// 2: the file ends in a CRC-32 of every byte before it (version 1 files, without, still read).
const VERSION: u32 = 2;

#[derive(serde::Serialize, serde::Deserialize)]
struct CheckpointHeader {
    iteration: u64,
    active_sh_degree: u32,
    sh_degree: u32,
    gaussians: usize,
    /// The run's configuration; keys an older checkpoint lacks take today's defaults.
    config: serde_json::Value,
    /// Instanced runs; then the offsets and their moments follow the statistics.
    #[serde(default)]
    layout: Option<Layout>,
    /// What it was trained on (checkpoints written before this was recorded have none).
    #[serde(default)]
    dataset: Option<DatasetIdentity>,
    /// Training views with a colour transform (0: none); their parameters, Adam moments and
    /// step counts follow the transforms.
    #[serde(default)]
    appearance_views: usize,
    /// The lens's vignetting (k1, k2), its Adam moments and step count (checkpoints written
    /// before it was learned have none: no vignetting).
    #[serde(default)]
    vignetting: Option<VignettingState>,
    /// The training cameras' corrections with their Adam moments and step counts (runs that
    /// refine none, and checkpoints written before cameras were refined, have none).
    #[serde(default)]
    cameras: Option<crate::train::cameras::CameraState>,
}

/// A checkpoint's vignetting state (crate::train::state::AppearanceState).
#[derive(serde::Serialize, serde::Deserialize)]
struct VignettingState {
    k: [f32; 2],
    exp_avg: [f32; 2],
    exp_avg_sq: [f32; 2],
    steps: u32,
}

/// Writes `st` atomically (temporary file + rename) after checking it is finite, so a bad state
/// never replaces the last good checkpoint; `dataset` is what it was trained on.
pub fn write_checkpoint(path: &Path, st: &TrainState, cfg: &Config, dataset: Option<&DatasetIdentity>) -> Result<()> {
    st.check_finite().context("checkpoint not written; the last good one is kept")?;
    let header = serde_json::to_vec(&CheckpointHeader {
        iteration: st.iteration,
        active_sh_degree: st.active_sh_degree,
        sh_degree: st.scene.sh_degree,
        gaussians: st.scene.len(),
        config: serde_json::to_value(cfg)?,
        layout: st.layout.clone(),
        dataset: dataset.cloned(),
        appearance_views: st.appearance.params.len(),
        vignetting: (!st.appearance.is_empty()).then(|| {
            let a = &st.appearance;
            VignettingState {
                k: a.vignetting,
                exp_avg: a.vignetting_exp_avg,
                exp_avg_sq: a.vignetting_exp_avg_sq,
                steps: a.vignetting_steps,
            }
        }),
        cameras: (!st.cameras.is_empty()).then(|| st.cameras.clone()),
    })?;
    crate::util::write_atomic(path, |f| {
        let mut w = CrcWriter { inner: std::io::BufWriter::new(f), crc: crc32fast::Hasher::new() };
        w.write_all(MAGIC)?;
        w.write_all(&VERSION.to_le_bytes())?;
        w.write_all(&(header.len() as u64).to_le_bytes())?;
        w.write_all(&header)?;
        let moments = st.exp_avg.iter().chain(&st.exp_avg_sq).map(|v| &v[..]);
        for arr in st.params().into_iter().chain(moments) {
            w.write_all(bytemuck::cast_slice(arr))?;
        }
        w.write_all(bytemuck::cast_slice(&st.grad2d_accum))?;
        w.write_all(bytemuck::cast_slice(&st.grad2d_count))?;
        w.write_all(bytemuck::cast_slice(&st.max_radii))?;
        let moments = st.offset_exp_avg.iter().chain(&st.offset_exp_avg_sq).map(|v| &v[..]);
        for arr in st.offset_arrays().into_iter().chain(moments) {
            w.write_all(bytemuck::cast_slice(arr))?;
        }
        for arr in [&st.xform_params, &st.xform_exp_avg, &st.xform_exp_avg_sq] {
            w.write_all(bytemuck::cast_slice(arr))?;
        }
        let a = &st.appearance;
        for arr in [&a.params, &a.exp_avg, &a.exp_avg_sq] {
            w.write_all(bytemuck::cast_slice(arr))?;
        }
        w.write_all(bytemuck::cast_slice(&a.steps))?;
        let crc = w.crc.clone().finalize();
        w.inner.write_all(&crc.to_le_bytes())?;
        w.inner.flush()
    })
}

/// A writer that keeps the CRC-32 of what went through it.
struct CrcWriter<W: Write> {
    inner: W,
    crc: crc32fast::Hasher,
}

impl<W: Write> Write for CrcWriter<W> {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        let n = self.inner.write(buf)?;
        self.crc.update(&buf[..n]);
        Ok(n)
    }
    fn flush(&mut self) -> std::io::Result<()> {
        self.inner.flush()
    }
}

/// Reads a checkpoint; returns the state and the configuration it was written with.
pub fn read_checkpoint(path: &Path) -> Result<(TrainState, Config)> {
    let data = std::fs::read(path).with_context(|| format!("{}: cannot read checkpoint", path.display()))?;
    checkpoint_from_bytes(&data, &path.display().to_string())
}

/// The dataset a checkpoint was trained on (`None` for checkpoints from before it was
/// recorded), reading only its header.
pub fn checkpoint_dataset(path: &Path) -> Result<Option<DatasetIdentity>> {
    use std::io::Read;
    let what = path.display().to_string();
    let mut f = std::fs::File::open(path).with_context(|| format!("{what}: cannot read checkpoint"))?;
    let mut head = [0u8; 20];
    f.read_exact(&mut head).map_err(|_| anyhow!("{what}: not an instgs-vk checkpoint"))?;
    let hlen = check_prefix(&head, &what)?;
    let mut header = Vec::new();
    f.take(hlen as u64).read_to_end(&mut header).with_context(|| format!("{what}: cannot read checkpoint"))?;
    Ok(parse_header(&header, hlen, &what)?.dataset)
}

/// Checks the magic and version; returns the header's length.
fn check_prefix(data: &[u8], what: &str) -> Result<usize> {
    if data.len() < 20 || &data[..8] != MAGIC {
        bail!("{what}: not an instgs-vk checkpoint");
    }
    let version = u32::from_le_bytes(data[8..12].try_into().unwrap());
    if version != 1 && version != VERSION {
        bail!("{what}: checkpoint version {version}, this build reads versions 1 and {VERSION}");
    }
    let hlen = u64::from_le_bytes(data[12..20].try_into().unwrap());
    usize::try_from(hlen).ok().filter(|&h| h <= (1 << 30)).ok_or_else(|| anyhow!("{what}: damaged checkpoint header"))
}

fn parse_header(bytes: &[u8], hlen: usize, what: &str) -> Result<CheckpointHeader> {
    let header: CheckpointHeader = (bytes.len() == hlen)
        .then(|| serde_json::from_slice(bytes).ok())
        .flatten()
        .ok_or_else(|| anyhow!("{what}: damaged checkpoint header"))?;
    if header.sh_degree > 3 || header.active_sh_degree > header.sh_degree {
        bail!("{what}: damaged checkpoint header");
    }
    Ok(header)
}

/// Whether the checkpoint at `path` is whole: its checksum matches its contents (version 1
/// files, which have none, count as whole). Nothing else is parsed.
pub fn checkpoint_is_whole(path: &Path) -> Result<bool> {
    let data = std::fs::read(path).with_context(|| format!("{}: cannot read checkpoint", path.display()))?;
    check_prefix(&data, &path.display().to_string())?;
    Ok(checked_body(&data).is_some())
}

/// The bytes before the checksum of a version-2 checkpoint when the checksum matches them
/// (version 1: all the bytes); None when it does not. `data` has passed [`check_prefix`].
fn checked_body(data: &[u8]) -> Option<&[u8]> {
    if u32::from_le_bytes(data[8..12].try_into().unwrap()) < 2 {
        return Some(data);
    }
    let body = &data[..data.len().saturating_sub(4).max(20)];
    let stored = data.get(body.len()..).and_then(|t| t.try_into().ok()).map(u32::from_le_bytes)?;
    (stored == crc32fast::hash(body)).then_some(body)
}

/// [`read_checkpoint`] on bytes in memory; `what` names them in errors.
pub fn checkpoint_from_bytes(data: &[u8], what: &str) -> Result<(TrainState, Config)> {
    let hlen = check_prefix(data, what)?;
    // Version 2: the last 4 bytes are the CRC-32 of the rest, checked before anything is read.
    let Some(data) = checked_body(data) else {
        bail!(
            "{what} is damaged: its checksum does not match its contents (a byte changed after it was written); remove it and train again (a pipeline: the same command with --from <its stage>)"
        );
    };
    let header = parse_header(data.get(20..).and_then(|d| d.get(..hlen)).unwrap_or_default(), hlen, what)?;
    let n = header.gaussians;
    let st = strides(header.sh_degree);
    let mut pos = 20 + hlen;
    let mut take = |count: Option<usize>| -> Result<&[u8]> {
        let bytes = count.and_then(|c| c.checked_mul(4)).ok_or_else(|| anyhow!("{what}: damaged checkpoint header"))?;
        let s = pos
            .checked_add(bytes)
            .and_then(|end| data.get(pos..end))
            .ok_or_else(|| anyhow!("{what}: truncated checkpoint"))?;
        pos += bytes;
        Ok(s)
    };
    let mut f32s = |count: Option<usize>| -> Result<Vec<f32>> { Ok(bytemuck::pod_collect_to_vec(take(count)?)) };
    let params: Vec<Vec<f32>> = (0..5).map(|k| f32s(n.checked_mul(st[k]))).collect::<Result<_>>()?;
    let m: Vec<Vec<f32>> = (0..5).map(|k| f32s(n.checked_mul(st[k]))).collect::<Result<_>>()?;
    let v: Vec<Vec<f32>> = (0..5).map(|k| f32s(n.checked_mul(st[k]))).collect::<Result<_>>()?;
    let stats = if header.layout.is_some() { 0 } else { n };
    let accum = f32s(Some(stats))?;
    let count: Vec<u32> = bytemuck::pod_collect_to_vec(&f32s(Some(stats))?);
    let radii: Vec<u32> = bytemuck::pod_collect_to_vec(&f32s(Some(stats))?);
    let pairs = match &header.layout {
        Some(l) => l.pairs().ok_or_else(|| anyhow!("{what}: damaged checkpoint header"))?,
        None => 0,
    };
    let ow = [3, 3, 1];
    let off: Vec<Vec<f32>> = (0..9).map(|k| f32s(pairs.checked_mul(ow[k % 3]))).collect::<Result<_>>()?;
    let instances = header
        .layout
        .as_ref()
        .map_or(Some(0), |l| l.groups.iter().try_fold(0usize, |a, g| a.checked_add(g.instances.len())));
    let xf: Vec<Vec<[f32; 8]>> = (0..3)
        .map(|_| Ok(bytemuck::pod_collect_to_vec(&f32s(instances.and_then(|i| i.checked_mul(8)))?)))
        .collect::<Result<_>>()?;
    let views = header.appearance_views;
    let ap: Vec<Vec<[f32; 12]>> =
        (0..3).map(|_| Ok(bytemuck::pod_collect_to_vec(&f32s(views.checked_mul(12))?))).collect::<Result<_>>()?;
    let steps: Vec<u32> = bytemuck::pod_collect_to_vec(&f32s(Some(views))?);
    if pos != data.len() {
        bail!("{what}: checkpoint has {} trailing bytes", data.len() - pos);
    }
    let to5 = |v: Vec<Vec<f32>>| -> [Vec<f32>; 5] { v.try_into().unwrap() };
    let none = VignettingState { k: [0.0; 2], exp_avg: [0.0; 2], exp_avg_sq: [0.0; 2], steps: 0 };
    let vig = header.vignetting.unwrap_or(none);
    let state = TrainState {
        iteration: header.iteration,
        active_sh_degree: header.active_sh_degree,
        scene: scene_from_params(to5(params), header.sh_degree),
        exp_avg: to5(m),
        exp_avg_sq: to5(v),
        grad2d_accum: accum,
        grad2d_count: count,
        max_radii: radii,
        layout: header.layout,
        offsets: Offsets {
            d_means: bytemuck::pod_collect_to_vec(&off[0]),
            d_sh0: bytemuck::pod_collect_to_vec(&off[1]),
            d_opacities: off[2].clone(),
        },
        offset_exp_avg: [off[3].clone(), off[4].clone(), off[5].clone()],
        offset_exp_avg_sq: [off[6].clone(), off[7].clone(), off[8].clone()],
        xform_params: xf[0].clone(),
        xform_exp_avg: xf[1].clone(),
        xform_exp_avg_sq: xf[2].clone(),
        appearance: AppearanceState {
            params: ap[0].clone(),
            exp_avg: ap[1].clone(),
            exp_avg_sq: ap[2].clone(),
            steps,
            free: [true; 12],
            vignetting: vig.k,
            vignetting_exp_avg: vig.exp_avg,
            vignetting_exp_avg_sq: vig.exp_avg_sq,
            vignetting_steps: vig.steps,
            vignetting_free: true,
        },
        cameras: header.cameras.unwrap_or_default(),
    };
    // Values checked at the door: a checkpoint with a NaN or infinity in its parameters, Adam
    // moments, offsets or transforms is damaged (training on it would only spread them).
    state.scene.validate(&format!("{what}: checkpoint"))?;
    let moments = state.exp_avg.iter().chain(&state.exp_avg_sq).flatten();
    let offsets = state.offset_exp_avg.iter().chain(&state.offset_exp_avg_sq).flatten();
    let deltas = state.offsets.d_means.iter().flatten().chain(state.offsets.d_sh0.iter().flatten());
    let xforms = state.xform_params.iter().chain(&state.xform_exp_avg).chain(&state.xform_exp_avg_sq).flatten();
    let a = &state.appearance;
    let colour = a.params.iter().chain(&a.exp_avg).chain(&a.exp_avg_sq).flatten();
    let c = &state.cameras;
    let n = c.deltas.len();
    if c.exp_avg.len() != n || c.exp_avg_sq.len() != n || c.steps.len() != n {
        bail!(
            "{what}: damaged checkpoint: {n} camera corrections with moments for {} and {}",
            c.exp_avg.len(),
            c.exp_avg_sq.len()
        );
    }
    let colour = colour.chain(c.deltas.iter().chain(&c.exp_avg).chain(&c.exp_avg_sq).flatten());
    if !moments
        .chain(offsets)
        .chain(deltas)
        .chain(&state.offsets.d_opacities)
        .chain(xforms)
        .chain(colour)
        .chain(&state.grad2d_accum)
        .all(|v| v.is_finite())
    {
        bail!(
            "{what}: damaged checkpoint: a non-finite value in its optimiser state, offsets, transforms, colour transforms or camera corrections"
        );
    }
    state.to_instanced().with_context(|| format!("{what}: damaged instanced checkpoint"))?;
    let config =
        Config::from_saved(header.config).with_context(|| format!("{what}: damaged checkpoint configuration"))?;
    Ok((state, config))
}

pub fn checkpoint_path(out: &Path) -> PathBuf {
    out.join("checkpoint.bin")
}
