//! Training datasets: NeRF-synthetic (`transforms_train.json` / `transforms_test.json`, RGB or
//! RGBA PNG composited over a background colour) and COLMAP (`sparse/0/cameras|images|points3D`
//! as `.bin` or `.txt`, images in `images/`).
//!
//! Cameras are converted to OpenCV (`viewmat` world → camera; COLMAP poses already are). Test
//! split: NeRF-synthetic's test file; for COLMAP every 8th image in name order (Inria's
//! `--eval`, llffhold 8). Initial points: `points3d.ply` (NeRF layout) or `points3D`.
//! Camera models: pinholes; photos through a distorting lens (COLMAP's SIMPLE_RADIAL, RADIAL,
//! OPENCV and fisheye models, nerfstudio's OPENCV and OPENCV_FISHEYE keys in a transforms file)
//! are undistorted on load onto a pinhole camera ([`lens`]); other models are refused.

mod colmap;
pub mod content;
pub mod lens;
pub mod masks;

pub use colmap::{colmap_intrinsics, read_colmap, read_colmap_file, ColmapCamera, ColmapImage, ColmapModel};
use std::io::BufRead;
use std::path::{Path, PathBuf};

use anyhow::{anyhow, bail, Context, Result};
use glam::{Mat3, Mat4, Quat, Vec3};

use crate::model::camera::{load_transforms_with_images, Camera, Lens};

/// One view: its camera and its image (linear [0, 1] RGB as stored, a = 1).
pub struct View {
    /// A pinhole: a photo through a distorting lens is undistorted on load (`undistort`).
    pub camera: Camera,
    pub image: Vec<[f32; 4]>,
    pub path: PathBuf,
    /// How the photo was undistorted (its masks are remapped the same way); None for a pinhole.
    pub undistort: Option<lens::Undistort>,
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
    /// The folder it was loaded from, as given.
    pub dir: PathBuf,
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
        let mut lenses: Vec<&str> = self
            .train
            .iter()
            .chain(&self.test)
            .filter_map(|v| Some(v.undistort.as_ref()?.source.lens.name()))
            .collect();
        lenses.sort_unstable();
        lenses.dedup();
        let undistorted = match lenses.is_empty() {
            true => String::new(),
            false => format!(", photos undistorted on load ({} lens onto a pinhole)", lenses.join(", ")),
        };
        Ok(format!(
            "{} dataset, {} training / {} test views at {}x{}{undistorted}",
            self.kind,
            self.train.len(),
            self.test.len(),
            first.camera.width,
            first.camera.height
        ))
    }

    /// What a training run depends on in this dataset, recorded in its checkpoints.
    pub fn identity(&self) -> DatasetIdentity {
        use sha2::{Digest, Sha256};
        let mut h = Sha256::new();
        for (split, views) in [("train", &self.train), ("test", &self.test)] {
            h.update(split.as_bytes());
            h.update((views.len() as u64).to_le_bytes());
            for v in views.iter() {
                let c = &v.camera;
                h.update((c.name.len() as u64).to_le_bytes());
                h.update(c.name.as_bytes());
                h.update(c.width.to_le_bytes());
                h.update(c.height.to_le_bytes());
                for x in [c.fx, c.fy, c.cx, c.cy].iter().chain(&c.viewmat.to_cols_array()) {
                    h.update(x.to_bits().to_le_bytes());
                }
            }
        }
        let first = self.train.first().map(|v| (v.camera.width, v.camera.height)).unwrap_or_default();
        DatasetIdentity {
            path: self.dir.display().to_string(),
            cameras: h.finalize().iter().map(|b| format!("{b:02x}")).collect(),
            train_views: self.train.len(),
            test_views: self.test.len(),
            width: first.0,
            height: first.1,
            images: None,
        }
    }

    pub fn split(&self, name: &str) -> Result<&[View]> {
        match name {
            "train" => Ok(&self.train),
            "test" => Ok(&self.test),
            other => bail!("unknown split '{other}' (train or test)"),
        }
    }
}

/// What a training run was trained on: its dataset folder (for messages; a moved dataset is the
/// same dataset), a SHA-256 of every camera of both splits (name, size, intrinsics, viewmat), the
/// view counts and the first training image's size after `--downscale`.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct DatasetIdentity {
    pub path: String,
    pub cameras: String,
    pub train_views: usize,
    pub test_views: usize,
    pub width: u32,
    pub height: u32,
    /// SHA-256 over every image's bytes ([`content::content_identity`]); checkpoints written
    /// before it was recorded have none.
    #[serde(default)]
    pub images: Option<String>,
}

impl DatasetIdentity {
    /// `None` when `now` is the dataset `self` describes; else what differs, in words.
    pub fn mismatch(&self, now: &DatasetIdentity) -> Option<String> {
        let was = format!("{} ({} training / {} test views", self.path, self.train_views, self.test_views);
        if (self.train_views, self.test_views) != (now.train_views, now.test_views) {
            Some(format!("{was}); {} has {} training / {} test views", now.path, now.train_views, now.test_views))
        } else if (self.width, self.height) != (now.width, now.height) {
            Some(format!(
                "{was} at {}x{}); {} is {}x{} (another --downscale?)",
                self.width, self.height, now.path, now.width, now.height
            ))
        } else if self.cameras != now.cameras {
            Some(format!("{was}); the cameras of {} differ", now.path))
        } else if self.images.is_some() && now.images.is_some() && self.images != now.images {
            Some(format!("{was}); the images of {} changed since (same names, other contents)", now.path))
        } else {
            None
        }
    }
}

/// Loads the dataset in `dir`, detecting its layout.
pub fn load(dir: &Path, opts: &LoadOptions) -> Result<Dataset> {
    if opts.downscale == 0 {
        bail!("--downscale must be at least 1");
    }
    match layout(dir)? {
        "nerf-synthetic" => load_nerf(dir, opts),
        _ => load_colmap(dir, opts),
    }
}

/// The layout of the dataset folder `dir` ("nerf-synthetic" or "colmap"), or why it is none.
pub fn layout(dir: &Path) -> Result<&'static str> {
    if dir.join("transforms_train.json").exists() {
        Ok("nerf-synthetic")
    } else if ["cameras.bin", "cameras.txt"].iter().any(|f| dir.join("sparse/0").join(f).exists()) {
        Ok("colmap")
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

/// Reads an image, checks its size against `cam`'s, undistorts it where `cam` has a lens,
/// composites alpha over `background` and downscales. Returns the pixels, the view's (pinhole)
/// camera after all that, and the undistortion.
fn load_image(
    path: &Path,
    cam: &Camera,
    opts: &LoadOptions,
) -> Result<(Vec<[f32; 4]>, Camera, Option<lens::Undistort>)> {
    let (width, height) = (cam.width, cam.height);
    let img = image::open(path).with_context(|| format!("{}: cannot read image", path.display()))?;
    if img.width() != width || img.height() != height {
        bail!("{}: image is {}x{}, the camera says {width}x{height}", path.display(), img.width(), img.height());
    }
    let mut rgba = img.to_rgba32f();
    let undistort = if cam.lens == Lens::Pinhole {
        None
    } else {
        let u = lens::Undistort::new(cam, &format!("{}: view {}", path.display(), cam.name))?;
        let px: Vec<[f32; 4]> = rgba.pixels().map(|p| p.0).collect();
        let flat: Vec<f32> = u.image(&px).into_iter().flatten().collect();
        rgba = image::Rgba32FImage::from_raw(width, height, flat).expect("same size");
        Some(u)
    };
    let mut camera = undistort.as_ref().map_or_else(|| cam.clone(), |u| u.target.clone());
    if opts.downscale > 1 {
        let (w, h) = (width / opts.downscale, height / opts.downscale);
        if w < MIN_IMAGE_SIDE || h < MIN_IMAGE_SIDE {
            bail!(
                "{}: --downscale {} makes this {width}x{height} image {w}x{h}; at most {} keeps both sides at {MIN_IMAGE_SIDE} pixels or more",
                path.display(),
                opts.downscale,
                width.min(height) / MIN_IMAGE_SIDE
            );
        }
        rgba = image::imageops::resize(&rgba, w, h, image::imageops::FilterType::Triangle);
        camera = camera.resized(w, h);
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
    Ok((px, camera, undistort))
}

/// The views' images, each a regular file inside `base` (the folder the file that names them
/// lies in; `crate::limits::inside`), which `referrer` names in errors.
fn load_views(list: Vec<(Camera, PathBuf)>, opts: &LoadOptions, referrer: &Path, base: &Path) -> Result<Vec<View>> {
    list.into_iter()
        .map(|(cam, path)| {
            if !path.exists() {
                bail!("{}: image of view '{}' is missing", path.display(), cam.name);
            }
            let what = referrer.display().to_string();
            crate::limits::inside(&what, &format!("the image of view '{}'", cam.name), &path, base)?;
            let (image, camera, undistort) = load_image(&path, &cam, opts)?;
            Ok(View { camera, image, path, undistort })
        })
        .collect()
}

fn load_nerf(dir: &Path, opts: &LoadOptions) -> Result<Dataset> {
    let train_file = dir.join("transforms_train.json");
    let train = load_views(load_transforms_with_images(&train_file)?, opts, &train_file, dir)?;
    let test_file = dir.join("transforms_test.json");
    let test = if test_file.exists() {
        load_views(load_transforms_with_images(&test_file)?, opts, &test_file, dir)?
    } else {
        Vec::new()
    };
    let ply = dir.join("points3d.ply");
    let points = if ply.exists() { Some(read_points_ply(&ply)?) } else { None };
    Ok(Dataset { kind: "nerf-synthetic", dir: dir.to_path_buf(), train, test, points })
}

/// `x y z` and `red green blue` (uchar or float) of a PLY point cloud.
pub fn read_points_ply(path: &Path) -> Result<PointCloud> {
    let what = path.display().to_string();
    let f = std::fs::File::open(path).with_context(|| format!("{what}: cannot open"))?;
    points_from_reader(std::io::BufReader::new(f), &what)
}

/// [`read_points_ply`] on bytes in memory; `what` names them in errors.
pub fn points_from_bytes(bytes: &[u8], what: &str) -> Result<PointCloud> {
    points_from_reader(bytes, what)
}

fn points_from_reader<R: BufRead>(r: R, what: &str) -> Result<PointCloud> {
    use ply_rs_bw::parser::Parser;
    use ply_rs_bw::ply::{DefaultElement, Property};
    let mut r = crate::formats::ply::checked_reader(r, what)?;
    let ply = Parser::<DefaultElement>::new()
        .read_ply(&mut r)
        .map_err(|e| anyhow!("{what}: not a PLY file: {}", e.to_string().lines().next().unwrap_or_default()))?;
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
        let mut c = [0.5f32; 3];
        for (k, name) in ["red", "green", "blue"].iter().enumerate() {
            if v.contains_key(*name) {
                let value = num(v, name)
                    .ok_or_else(|| anyhow!("{what}: vertex property '{name}' must be a uchar, float or double"))?;
                if !value.is_finite() {
                    bail!("{what}: vertex {i} has a non-finite {name}");
                }
                c[k] = value.clamp(0.0, 1.0);
            }
        }
        pc.positions.push([x, y, z]);
        pc.colours.push(c);
    }
    Ok(pc)
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
            let (intr, lens) = colmap_intrinsics(cam, &format!("{}: camera {}", sparse.display(), im.camera_id))?;
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
                lens,
            };
            camera.validate().with_context(|| format!("{}: image {}", sparse.display(), im.name))?;
            let what = sparse.display().to_string();
            crate::limits::relative(&what, "an image's name", &im.name, &dir.join("images"))?;
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
    Ok(Dataset {
        kind: "colmap",
        dir: dir.to_path_buf(),
        train: load_views(train, opts, &dir.join("sparse/0"), &dir.join("images"))?,
        test: load_views(test, opts, &dir.join("sparse/0"), &dir.join("images"))?,
        points,
    })
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
    let layout = layout(path).ok();
    if layout == Some("nerf-synthetic") {
        let names = if split == "all" { vec!["train", "val", "test"] } else { vec![split] };
        let mut cams = Vec::new();
        for n in names {
            let f = path.join(format!("transforms_{n}.json"));
            if f.exists() || split != "all" {
                cams.extend(crate::model::camera::load_transforms_with_images(&f)?);
            }
        }
        Ok(cams)
    } else if layout == Some("colmap") {
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

/// [`dataset_cameras_with_images`] without the image files, as the rasterizer draws them: a
/// camera with a lens becomes the pinhole camera its photo is undistorted onto when the dataset
/// is loaded (the same view training and `eval` see), and a note says so once.
pub fn dataset_cameras(path: &Path, split: &str) -> Result<Vec<Camera>> {
    let cams: Vec<Camera> = dataset_cameras_with_images(path, split)?.into_iter().map(|(c, _)| c).collect();
    if let Some(c) = cams.iter().find(|c| c.lens != Lens::Pinhole) {
        eprintln!(
            "note: {}: the cameras carry lens distortion ({}); renders are pinhole images, of the undistorted views that training and eval use (their photos are undistorted on load), not of the distorted photos",
            path.display(),
            c.lens.name()
        );
    }
    cams.into_iter()
        .map(|c| match c.lens {
            Lens::Pinhole => Ok(c),
            _ => {
                let what = format!("{}: camera {}", path.display(), c.name);
                Ok(lens::Undistort::new(&c, &what)?.target)
            }
        })
        .collect()
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
