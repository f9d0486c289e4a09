//! Training datasets: NeRF-synthetic (`transforms_train.json` / `transforms_test.json`, RGB or
//! RGBA PNG composited over a background colour) and COLMAP (`sparse/0/cameras|images|points3D`
//! as `.bin` or `.txt`, images in `images/`).
//!
//! Cameras are converted to OpenCV (`viewmat` world → camera; COLMAP poses already are). Test
//! split: NeRF-synthetic's test file; for COLMAP every 8th image in name order (Inria's
//! `--eval`, llffhold 8). Initial points: `points3d.ply` (NeRF layout) or `points3D`.
//! Camera models: PINHOLE and SIMPLE_PINHOLE; SIMPLE_RADIAL, RADIAL and OPENCV whose distortion
//! moves no image corner by more than [`MAX_IGNORED_DISTORTION_PX`] are used as pinholes with a
//! warning; others are refused (undistort with `colmap image_undistorter`).

pub mod masks;
use std::io::{BufRead, Read};
use std::path::{Path, PathBuf};

use anyhow::{anyhow, bail, Context, Result};
use glam::{Mat3, Mat4, Quat, Vec3};

use crate::model::camera::{load_transforms_with_images, Camera};

/// Largest distortion displacement (pixels, at the image corners) treated as none.
pub const MAX_IGNORED_DISTORTION_PX: f32 = 0.5;

/// One view: its camera and its image (linear [0, 1] RGB as stored, a = 1).
pub struct View {
    pub camera: Camera,
    pub image: Vec<[f32; 4]>,
    pub path: PathBuf,
}

/// Coloured points for initialisation.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PointCloud {
    pub positions: Vec<[f32; 3]>,
    /// RGB in [0, 1].
    pub colours: Vec<[f32; 3]>,
}

pub struct Dataset {
    /// "nerf-synthetic" or "colmap".
    pub kind: &'static str,
    pub train: Vec<View>,
    pub test: Vec<View>,
    pub points: Option<PointCloud>,
}

#[derive(Clone, Copy, Debug)]
pub struct LoadOptions {
    /// Integer factor: images and intrinsics are divided by it (1 = full resolution).
    pub downscale: u32,
    /// RGB composited under transparent pixels of RGBA images.
    pub background: [f32; 3],
}

impl Dataset {
    /// Inria's camera extent: 1.1 × the largest distance of a training camera centre from
    /// their mean (`getNerfppNorm`).
    pub fn camera_extent(&self) -> f32 {
        let centres: Vec<Vec3> = self.train.iter().map(|v| v.camera.position()).collect();
        let mean = centres.iter().copied().sum::<Vec3>() / centres.len().max(1) as f32;
        let d = centres.iter().map(|c| c.distance(mean)).fold(0.0, f32::max);
        1.1 * d.max(1e-3)
    }

    /// "nerf-synthetic dataset, 48 training / 12 test views at 320x240"; training views required
    /// (`dir` names the dataset in the error).
    pub fn describe(&self, dir: &Path) -> Result<String> {
        let Some(first) = self.train.first() else { bail!("{}: the dataset has no training views", dir.display()) };
        Ok(format!(
            "{} dataset, {} training / {} test views at {}x{}",
            self.kind,
            self.train.len(),
            self.test.len(),
            first.camera.width,
            first.camera.height
        ))
    }

    pub fn split(&self, name: &str) -> Result<&[View]> {
        match name {
            "train" => Ok(&self.train),
            "test" => Ok(&self.test),
            other => bail!("unknown split '{other}' (train or test)"),
        }
    }
}

/// Loads the dataset in `dir`, detecting its layout.
pub fn load(dir: &Path, opts: &LoadOptions) -> Result<Dataset> {
    if opts.downscale == 0 {
        bail!("--downscale must be at least 1");
    }
    if dir.join("transforms_train.json").exists() {
        load_nerf(dir, opts)
    } else if ["cameras.bin", "cameras.txt"].iter().any(|f| dir.join("sparse/0").join(f).exists()) {
        load_colmap(dir, opts)
    } else if !dir.is_dir() {
        bail!("{}: no such directory", dir.display())
    } else {
        bail!(
            "{}: not a dataset: expected transforms_train.json (NeRF-synthetic) or sparse/0/cameras.bin|txt (COLMAP)",
            dir.display()
        )
    }
}

/// The smallest image side `--downscale` may leave (one 16×16 tile).
pub const MIN_IMAGE_SIDE: u32 = 16;

/// Reads an image, checks its size, composites alpha over `background` and downscales.
fn load_image(path: &Path, width: u32, height: u32, opts: &LoadOptions) -> Result<(Vec<[f32; 4]>, u32, u32)> {
    let img = image::open(path).with_context(|| format!("{}: cannot read image", path.display()))?;
    if img.width() != width || img.height() != height {
        bail!("{}: image is {}x{}, the camera says {width}x{height}", path.display(), img.width(), img.height());
    }
    let mut rgba = img.to_rgba32f();
    let (mut w, mut h) = (width, height);
    if opts.downscale > 1 {
        w = width / opts.downscale;
        h = height / opts.downscale;
        if w < MIN_IMAGE_SIDE || h < MIN_IMAGE_SIDE {
            bail!(
                "{}: --downscale {} makes this {width}x{height} image {w}x{h}; at most {} keeps both sides at {MIN_IMAGE_SIDE} pixels or more",
                path.display(),
                opts.downscale,
                width.min(height) / MIN_IMAGE_SIDE
            );
        }
        rgba = image::imageops::resize(&rgba, w, h, image::imageops::FilterType::Triangle);
    }
    let bg = opts.background;
    let px = rgba
        .pixels()
        .map(|p| {
            let a = p.0[3];
            [0, 1, 2].map(|c| p.0[c] * a + bg[c] * (1.0 - a)).map(|v| v.clamp(0.0, 1.0))
        })
        .map(|c| [c[0], c[1], c[2], 1.0])
        .collect();
    Ok((px, w, h))
}

fn load_views(list: Vec<(Camera, PathBuf)>, opts: &LoadOptions) -> Result<Vec<View>> {
    list.into_iter()
        .map(|(cam, path)| {
            if !path.exists() {
                bail!("{}: image of view '{}' is missing", path.display(), cam.name);
            }
            let (image, w, h) = load_image(&path, cam.width, cam.height, opts)?;
            Ok(View { camera: cam.resized(w, h), image, path })
        })
        .collect()
}

fn load_nerf(dir: &Path, opts: &LoadOptions) -> Result<Dataset> {
    let train = load_views(load_transforms_with_images(&dir.join("transforms_train.json"))?, opts)?;
    let test_file = dir.join("transforms_test.json");
    let test =
        if test_file.exists() { load_views(load_transforms_with_images(&test_file)?, opts)? } else { Vec::new() };
    let ply = dir.join("points3d.ply");
    let points = if ply.exists() { Some(read_points_ply(&ply)?) } else { None };
    Ok(Dataset { kind: "nerf-synthetic", train, test, points })
}

/// `x y z` and `red green blue` (uchar or float) of a PLY point cloud.
pub fn read_points_ply(path: &Path) -> Result<PointCloud> {
    use ply_rs_bw::parser::Parser;
    use ply_rs_bw::ply::{DefaultElement, Property};
    let what = path.display();
    let f = std::fs::File::open(path).with_context(|| format!("{what}: cannot open"))?;
    let mut r = std::io::BufReader::new(f);
    let ply = Parser::<DefaultElement>::new().read_ply(&mut r).map_err(|e| anyhow!("{what}: not a PLY file: {e}"))?;
    let verts = ply.payload.get("vertex").ok_or_else(|| anyhow!("{what}: no vertex element"))?;
    let num = |e: &DefaultElement, k: &str| -> Option<f32> {
        match e.get(k)? {
            Property::Float(v) => Some(*v),
            Property::Double(v) => Some(*v as f32),
            Property::UChar(v) => Some(*v as f32 / 255.0),
            _ => None,
        }
    };
    let mut pc = PointCloud::default();
    for (i, v) in verts.iter().enumerate() {
        let p = [num(v, "x"), num(v, "y"), num(v, "z")];
        let [Some(x), Some(y), Some(z)] = p else { bail!("{what}: vertex {i} lacks float x, y, z") };
        if !(x.is_finite() && y.is_finite() && z.is_finite()) {
            bail!("{what}: vertex {i} is not finite");
        }
        let c = [num(v, "red"), num(v, "green"), num(v, "blue")];
        pc.positions.push([x, y, z]);
        pc.colours.push(c.map(|c| c.unwrap_or(0.5).clamp(0.0, 1.0)));
    }
    Ok(pc)
}

/// A COLMAP camera: model name, size and parameters.
#[derive(Clone, Debug, PartialEq)]
pub struct ColmapCamera {
    pub model: String,
    pub width: u32,
    pub height: u32,
    pub params: Vec<f64>,
}

/// A registered COLMAP image: world → camera rotation (w, x, y, z) and translation.
#[derive(Clone, Debug, PartialEq)]
pub struct ColmapImage {
    pub qvec: [f64; 4],
    pub tvec: [f64; 3],
    pub camera_id: u32,
    pub name: String,
}

/// The three files of a COLMAP sparse model.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ColmapModel {
    pub cameras: std::collections::BTreeMap<u32, ColmapCamera>,
    pub images: Vec<ColmapImage>,
    pub points: PointCloud,
}

const MODELS: [(&str, usize); 11] = [
    ("SIMPLE_PINHOLE", 3),
    ("PINHOLE", 4),
    ("SIMPLE_RADIAL", 4),
    ("RADIAL", 5),
    ("OPENCV", 8),
    ("OPENCV_FISHEYE", 8),
    ("FULL_OPENCV", 12),
    ("FOV", 5),
    ("SIMPLE_RADIAL_FISHEYE", 4),
    ("RADIAL_FISHEYE", 5),
    ("THIN_PRISM_FISHEYE", 12),
];

struct Bin<'a> {
    data: &'a [u8],
    pos: usize,
    what: String,
}

impl Bin<'_> {
    fn take<const N: usize>(&mut self) -> Result<[u8; N]> {
        let s = self
            .data
            .get(self.pos..self.pos + N)
            .ok_or_else(|| anyhow!("{}: truncated at byte {}", self.what, self.pos))?;
        self.pos += N;
        Ok(s.try_into().unwrap())
    }
    fn u64(&mut self) -> Result<u64> {
        Ok(u64::from_le_bytes(self.take()?))
    }
    fn i32(&mut self) -> Result<i32> {
        Ok(i32::from_le_bytes(self.take()?))
    }
    fn f64(&mut self) -> Result<f64> {
        Ok(f64::from_le_bytes(self.take()?))
    }
    fn u8(&mut self) -> Result<u8> {
        Ok(self.take::<1>()?[0])
    }
    fn skip(&mut self, n: u64) -> Result<()> {
        let end = (self.pos as u64).checked_add(n).filter(|&e| e <= self.data.len() as u64);
        self.pos = end.ok_or_else(|| anyhow!("{}: truncated at byte {}", self.what, self.pos))? as usize;
        Ok(())
    }
    fn count(&mut self, item_bytes: u64) -> Result<u64> {
        let n = self.u64()?;
        if n.saturating_mul(item_bytes) > (self.data.len() - self.pos) as u64 {
            bail!("{}: claims {n} entries, more than the file holds", self.what);
        }
        Ok(n)
    }
}

fn read_file(path: &Path) -> Result<Vec<u8>> {
    let mut v = Vec::new();
    std::fs::File::open(path)
        .and_then(|mut f| f.read_to_end(&mut v))
        .with_context(|| format!("{}: cannot read", path.display()))?;
    Ok(v)
}

/// Reads `dir/cameras|images|points3D` (`.bin` preferred, else `.txt`).
pub fn read_colmap(dir: &Path) -> Result<ColmapModel> {
    let bin = dir.join("cameras.bin").exists();
    let mut m = ColmapModel::default();
    if bin {
        let path = dir.join("cameras.bin");
        let data = read_file(&path)?;
        let mut b = Bin { data: &data, pos: 0, what: path.display().to_string() };
        for _ in 0..b.count(24)? {
            let id = b.i32()? as u32;
            let model_id = b.i32()?;
            let (w, h) = (b.u64()?, b.u64()?);
            let &(model, np) = MODELS
                .get(model_id as usize)
                .ok_or_else(|| anyhow!("{}: camera {id} has unknown model id {model_id}", b.what))?;
            let params = (0..np).map(|_| b.f64()).collect::<Result<Vec<_>>>()?;
            m.cameras.insert(id, ColmapCamera { model: model.into(), width: w as u32, height: h as u32, params });
        }
        let path = dir.join("images.bin");
        let data = read_file(&path)?;
        let mut b = Bin { data: &data, pos: 0, what: path.display().to_string() };
        for _ in 0..b.count(64)? {
            let _id = b.i32()?;
            let qvec = [b.f64()?, b.f64()?, b.f64()?, b.f64()?];
            let tvec = [b.f64()?, b.f64()?, b.f64()?];
            let camera_id = b.i32()? as u32;
            let mut name = Vec::new();
            loop {
                match b.u8()? {
                    0 => break,
                    c => name.push(c),
                }
            }
            let np = b.count(24)?;
            b.skip(np * 24)?;
            m.images.push(ColmapImage { qvec, tvec, camera_id, name: String::from_utf8_lossy(&name).into_owned() });
        }
        let path = dir.join("points3D.bin");
        if path.exists() {
            let data = read_file(&path)?;
            let mut b = Bin { data: &data, pos: 0, what: path.display().to_string() };
            for _ in 0..b.count(43)? {
                let _id = b.u64()?;
                let p = [b.f64()? as f32, b.f64()? as f32, b.f64()? as f32];
                let c = [b.u8()?, b.u8()?, b.u8()?].map(|v| v as f32 / 255.0);
                let _err = b.f64()?;
                let track = b.count(8)?;
                b.skip(track * 8)?;
                if !p.iter().all(|v| v.is_finite()) {
                    bail!("{}: point {_id} has a non-finite position {p:?}", path.display());
                }
                m.points.positions.push(p);
                m.points.colours.push(c);
            }
        }
    } else {
        let lines = |name: &str| -> Result<Vec<(usize, String)>> {
            let path = dir.join(name);
            let f = std::fs::File::open(&path).with_context(|| format!("{}: cannot read", path.display()))?;
            let mut out = Vec::new();
            for (i, l) in std::io::BufReader::new(f).lines().enumerate() {
                let l = l.with_context(|| format!("{}: line {}", path.display(), i + 1))?;
                out.push((i + 1, l));
            }
            Ok(out)
        };
        let bad = |file: &str, line: usize, why: &str| anyhow!("{}: line {line}: {why}", dir.join(file).display());
        for (no, l) in lines("cameras.txt")? {
            let t: Vec<&str> = l.split_whitespace().collect();
            if t.is_empty() || t[0].starts_with('#') {
                continue;
            }
            let parse_err = || bad("cameras.txt", no, "expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]");
            if t.len() < 4 {
                return Err(parse_err());
            }
            let id: u32 = t[0].parse().map_err(|_| parse_err())?;
            let np = MODELS
                .iter()
                .find(|m| m.0 == t[1])
                .ok_or_else(|| bad("cameras.txt", no, &format!("unknown camera model {}", t[1])))?
                .1;
            let params: Vec<f64> =
                t[4..].iter().map(|v| v.parse()).collect::<Result<_, _>>().map_err(|_| parse_err())?;
            if params.len() != np {
                return Err(bad("cameras.txt", no, &format!("{} takes {np} parameters, got {}", t[1], params.len())));
            }
            m.cameras.insert(
                id,
                ColmapCamera {
                    model: t[1].into(),
                    width: t[2].parse().map_err(|_| parse_err())?,
                    height: t[3].parse().map_err(|_| parse_err())?,
                    params,
                },
            );
        }
        let mut expect_points = false;
        for (no, l) in lines("images.txt")? {
            if l.trim_start().starts_with('#') {
                continue;
            }
            if expect_points {
                expect_points = false;
                continue;
            }
            let t: Vec<&str> = l.split_whitespace().collect();
            if t.is_empty() {
                continue;
            }
            let parse_err = || bad("images.txt", no, "expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME");
            if t.len() < 10 {
                return Err(parse_err());
            }
            let f: Vec<f64> = t[1..8].iter().map(|v| v.parse()).collect::<Result<_, _>>().map_err(|_| parse_err())?;
            m.images.push(ColmapImage {
                qvec: [f[0], f[1], f[2], f[3]],
                tvec: [f[4], f[5], f[6]],
                camera_id: t[8].parse().map_err(|_| parse_err())?,
                name: t[9..].join(" "),
            });
            expect_points = true;
        }
        if dir.join("points3D.txt").exists() {
            for (no, l) in lines("points3D.txt")? {
                let t: Vec<&str> = l.split_whitespace().collect();
                if t.is_empty() || t[0].starts_with('#') {
                    continue;
                }
                let parse_err = || bad("points3D.txt", no, "expected POINT3D_ID X Y Z R G B ERROR TRACK[]");
                if t.len() < 8 {
                    return Err(parse_err());
                }
                let f: Vec<f32> =
                    t[1..7].iter().map(|v| v.parse()).collect::<Result<_, _>>().map_err(|_| parse_err())?;
                if !f[..3].iter().all(|v| v.is_finite()) {
                    return Err(bad("points3D.txt", no, "the point's position is not finite"));
                }
                m.points.positions.push([f[0], f[1], f[2]]);
                m.points.colours.push([f[3] / 255.0, f[4] / 255.0, f[5] / 255.0]);
            }
        }
    }
    if m.images.is_empty() {
        bail!("{}: the COLMAP model has no registered images", dir.display());
    }
    Ok(m)
}

/// Pinhole intrinsics (fx, fy, cx, cy) of a COLMAP camera, or an error for models that are not
/// (nearly) pinhole. `what` names the camera in messages.
pub fn pinhole(cam: &ColmapCamera, what: &str) -> Result<[f32; 4]> {
    let p = &cam.params;
    let (f, distortion): ([f64; 4], Vec<f64>) = match cam.model.as_str() {
        "SIMPLE_PINHOLE" => ([p[0], p[0], p[1], p[2]], vec![]),
        "PINHOLE" => ([p[0], p[1], p[2], p[3]], vec![]),
        "SIMPLE_RADIAL" => ([p[0], p[0], p[1], p[2]], vec![p[3], 0.0, 0.0, 0.0]),
        "RADIAL" => ([p[0], p[0], p[1], p[2]], vec![p[3], p[4], 0.0, 0.0]),
        "OPENCV" => ([p[0], p[1], p[2], p[3]], vec![p[4], p[5], p[6], p[7]]),
        other => bail!(
            "{what}: camera model {other} is not supported; undistort the images to PINHOLE first (colmap image_undistorter)"
        ),
    };
    if !distortion.is_empty() {
        // Largest displacement of an image corner under the distortion (pixels).
        let [fx, fy, cx, cy] = f;
        let [k1, k2, p1, p2] = [distortion[0], distortion[1], distortion[2], distortion[3]];
        let mut worst = 0.0f64;
        for (u, v) in
            [(0.0, 0.0), (cam.width as f64, 0.0), (0.0, cam.height as f64), (cam.width as f64, cam.height as f64)]
        {
            let (x, y) = ((u - cx) / fx, (v - cy) / fy);
            let r2 = x * x + y * y;
            let radial = k1 * r2 + k2 * r2 * r2;
            let dx = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x);
            let dy = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y;
            worst = worst.max((dx * fx).hypot(dy * fy));
        }
        if worst > MAX_IGNORED_DISTORTION_PX as f64 {
            bail!(
                "{what}: {} distortion moves the image corners by up to {worst:.1} px; undistort the images first (colmap image_undistorter) and train on the PINHOLE model",
                cam.model
            );
        }
        if worst > 0.0 {
            eprintln!(
                "warning: {what}: {} distortion (≤ {worst:.2} px at the corners) is ignored; treated as a pinhole",
                cam.model
            );
        }
    }
    Ok(f.map(|v| v as f32))
}

/// Every registered image of a COLMAP model as (camera, image path), sorted by image name.
fn colmap_cameras(dir: &Path, model: &ColmapModel) -> Result<Vec<(Camera, PathBuf)>> {
    let sparse = dir.join("sparse/0");
    let mut images = model.images.clone();
    images.sort_by(|a, b| a.name.cmp(&b.name));
    images
        .iter()
        .map(|im| {
            let cam = model.cameras.get(&im.camera_id).ok_or_else(|| {
                anyhow!(
                    "{}: image {} refers to camera {}, which cameras.* lacks",
                    sparse.display(),
                    im.name,
                    im.camera_id
                )
            })?;
            let intr = pinhole(cam, &format!("{}: camera {}", sparse.display(), im.camera_id))?;
            let [w, x, y, z] = im.qvec.map(|v| v as f32);
            let rot = Mat3::from_quat(Quat::from_xyzw(x, y, z, w).normalize());
            let t = Vec3::new(im.tvec[0] as f32, im.tvec[1] as f32, im.tvec[2] as f32);
            let viewmat =
                Mat4::from_cols(rot.x_axis.extend(0.0), rot.y_axis.extend(0.0), rot.z_axis.extend(0.0), t.extend(1.0));
            let name = Path::new(&im.name).file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
            let camera = Camera {
                name,
                width: cam.width,
                height: cam.height,
                fx: intr[0],
                fy: intr[1],
                cx: intr[2],
                cy: intr[3],
                viewmat,
            };
            camera.validate().with_context(|| format!("{}: image {}", sparse.display(), im.name))?;
            Ok((camera, dir.join("images").join(&im.name)))
        })
        .collect()
}

fn load_colmap(dir: &Path, opts: &LoadOptions) -> Result<Dataset> {
    let model = read_colmap(&dir.join("sparse/0"))?;
    let mut train = Vec::new();
    let mut test = Vec::new();
    for (k, view) in colmap_cameras(dir, &model)?.into_iter().enumerate() {
        if k % 8 == 0 {
            test.push(view);
        } else {
            train.push(view);
        }
    }
    let points = (!model.points.positions.is_empty()).then_some(model.points);
    Ok(Dataset { kind: "colmap", train: load_views(train, opts)?, test: load_views(test, opts)?, points })
}

/// The cameras of a dataset without loading its images, with their image files: a
/// NeRF-synthetic folder's `transforms_<split>.json` (`all`: train, val and test), a COLMAP
/// folder's images (its test split is every 8th image by name, as [`load`] holds out; `all`:
/// every image), or a transforms JSON file itself (all its frames; `split` is not used).
pub fn dataset_cameras_with_images(path: &Path, split: &str) -> Result<Vec<(Camera, PathBuf)>> {
    if !["train", "test", "all"].contains(&split) {
        bail!("split '{split}': expected train, test or all");
    }
    if path.is_file() {
        return crate::model::camera::load_transforms_with_images(path);
    }
    if path.join("transforms_train.json").exists() {
        let names = if split == "all" { vec!["train", "val", "test"] } else { vec![split] };
        let mut cams = Vec::new();
        for n in names {
            let f = path.join(format!("transforms_{n}.json"));
            if f.exists() || split != "all" {
                cams.extend(crate::model::camera::load_transforms_with_images(&f)?);
            }
        }
        Ok(cams)
    } else if ["cameras.bin", "cameras.txt"].iter().any(|f| path.join("sparse/0").join(f).exists()) {
        let model = read_colmap(&path.join("sparse/0"))?;
        Ok(colmap_cameras(path, &model)?
            .into_iter()
            .enumerate()
            .filter(|(k, _)| match split {
                "train" => k % 8 != 0,
                "test" => k % 8 == 0,
                _ => true,
            })
            .map(|(_, c)| c)
            .collect())
    } else {
        bail!(
            "{}: no cameras: expected a transforms_*.json file, or a folder with transforms_train.json (NeRF-synthetic) or sparse/0/cameras.bin|txt (COLMAP)",
            path.display()
        )
    }
}

/// [`dataset_cameras_with_images`] without the image files.
pub fn dataset_cameras(path: &Path, split: &str) -> Result<Vec<Camera>> {
    Ok(dataset_cameras_with_images(path, split)?.into_iter().map(|(c, _)| c).collect())
}

/// `instgs-vk cameras`: the cameras of `data`'s `split` as a transforms.json (OpenGL c2w,
/// per-frame intrinsics, absolute image paths).
pub fn export_cameras(data: &Path, split: &str, out: &Path) -> Result<()> {
    let cams = crate::dataset::dataset_cameras_with_images(data, split)?;
    if cams.is_empty() {
        bail!("{}: the {split} split has no cameras", data.display());
    }
    let images: Vec<String> = cams
        .iter()
        .map(|(_, p)| std::fs::canonicalize(p).unwrap_or_else(|_| p.clone()).display().to_string())
        .collect();
    let cams: Vec<Camera> = cams.into_iter().map(|(c, _)| c).collect();
    crate::util::write_json(out, &crate::model::camera::transforms_json(&cams, &images), true)?;
    eprintln!("wrote {} ({} cameras)", out.display(), cams.len());
    Ok(())
}
