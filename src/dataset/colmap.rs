//! COLMAP's sparse model (`cameras`, `images`, `points3D` as `.bin` or `.txt`), read with every
//! count, size and value checked, and its camera models' intrinsics and lenses.
use std::io::Read;
use std::path::Path;

use anyhow::{anyhow, bail, Context, Result};

use super::PointCloud;
use crate::model::camera::Lens;

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
    /// Refuses bytes after the last entry (a count that disagrees with the data).
    fn end(&self) -> Result<()> {
        if self.pos != self.data.len() {
            bail!("{}: {} bytes follow the last entry the file counts", self.what, self.data.len() - self.pos);
        }
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

/// Reads `dir/cameras|images|points3D` (`.bin` preferred, else `.txt`; `points3D` optional).
pub fn read_colmap(dir: &Path) -> Result<ColmapModel> {
    let ext = if dir.join("cameras.bin").exists() { "bin" } else { "txt" };
    let mut m = ColmapModel::default();
    for file in ["cameras", "images", "points3D"] {
        let path = dir.join(format!("{file}.{ext}"));
        if file == "points3D" && !path.exists() {
            continue;
        }
        read_colmap_file(&mut m, file, ext == "bin", &read_file(&path)?, &path.display().to_string())?;
    }
    if m.images.is_empty() {
        bail!("{}: the COLMAP model has no registered images", dir.display());
    }
    Ok(m)
}

/// Adds one COLMAP file (`file` is `cameras`, `images` or `points3D`; binary or text) to `m`;
/// `what` names it in errors.
pub fn read_colmap_file(m: &mut ColmapModel, file: &str, binary: bool, data: &[u8], what: &str) -> Result<()> {
    let text = || std::str::from_utf8(data).map_err(|e| anyhow!("{what}: not UTF-8 text: {e}"));
    match (file, binary) {
        ("cameras", true) => colmap_cameras_bin(m, data, what),
        ("images", true) => colmap_images_bin(m, data, what),
        ("points3D", true) => colmap_points_bin(m, data, what),
        ("cameras", false) => colmap_cameras_txt(m, text()?, what),
        ("images", false) => colmap_images_txt(m, text()?, what),
        ("points3D", false) => colmap_points_txt(m, text()?, what),
        _ => bail!("{what}: not a COLMAP model file"),
    }
}

/// A camera's size and parameters, checked: sides 1..=65535 pixels, finite parameters.
fn colmap_camera(what: &str, id: u32, model: &str, w: u64, h: u64, params: Vec<f64>) -> Result<ColmapCamera> {
    if !(1..=65535).contains(&w) || !(1..=65535).contains(&h) {
        bail!("{what}: camera {id} is {w}x{h} pixels; expected sides of 1 to 65535");
    }
    if let Some(v) = params.iter().find(|v| !v.is_finite()) {
        bail!("{what}: camera {id} has a non-finite parameter {v}");
    }
    Ok(ColmapCamera { model: model.into(), width: w as u32, height: h as u32, params })
}

fn insert_camera(m: &mut ColmapModel, what: &str, id: u32, cam: ColmapCamera) -> Result<()> {
    if m.cameras.insert(id, cam).is_some() {
        bail!("{what}: camera {id} is listed twice");
    }
    Ok(())
}

fn colmap_image(what: &str, name: &str, qvec: [f64; 4], tvec: [f64; 3], camera_id: u32) -> Result<ColmapImage> {
    if !qvec.iter().chain(&tvec).all(|v| v.is_finite()) {
        bail!("{what}: image {name} has a non-finite pose");
    }
    let norm = qvec.iter().map(|v| v * v).sum::<f64>().sqrt();
    if norm <= 1e-6 {
        bail!("{what}: image {name} has a zero rotation quaternion");
    }
    if name.is_empty() {
        bail!("{what}: an image has an empty name");
    }
    Ok(ColmapImage { qvec, tvec, camera_id, name: name.to_string() })
}

fn colmap_cameras_bin(m: &mut ColmapModel, data: &[u8], what: &str) -> Result<()> {
    let mut b = Bin { data, pos: 0, what: what.to_string() };
    for _ in 0..b.count(24)? {
        let id = b.i32()?;
        let id = u32::try_from(id).map_err(|_| anyhow!("{what}: camera id {id} is negative"))?;
        let model_id = b.i32()?;
        let (w, h) = (b.u64()?, b.u64()?);
        let &(model, np) = usize::try_from(model_id)
            .ok()
            .and_then(|i| MODELS.get(i))
            .ok_or_else(|| anyhow!("{what}: camera {id} has unknown model id {model_id}"))?;
        let params = (0..np).map(|_| b.f64()).collect::<Result<Vec<_>>>()?;
        insert_camera(m, what, id, colmap_camera(what, id, model, w, h, params)?)?;
    }
    b.end()
}

fn colmap_images_bin(m: &mut ColmapModel, data: &[u8], what: &str) -> Result<()> {
    let mut b = Bin { data, pos: 0, what: what.to_string() };
    for _ in 0..b.count(64)? {
        let _id = b.i32()?;
        let qvec = [b.f64()?, b.f64()?, b.f64()?, b.f64()?];
        let tvec = [b.f64()?, b.f64()?, b.f64()?];
        let camera_id = b.i32()?;
        let camera_id = u32::try_from(camera_id)
            .map_err(|_| anyhow!("{what}: an image names camera {camera_id}, a negative id"))?;
        let mut name = Vec::new();
        loop {
            match b.u8()? {
                0 => break,
                c => name.push(c),
            }
        }
        let np = b.count(24)?;
        b.skip(np * 24)?;
        let name = String::from_utf8(name).map_err(|_| anyhow!("{what}: an image name is not UTF-8"))?;
        m.images.push(colmap_image(what, &name, qvec, tvec, camera_id)?);
    }
    b.end()
}

fn colmap_points_bin(m: &mut ColmapModel, data: &[u8], what: &str) -> Result<()> {
    let mut b = Bin { data, pos: 0, what: what.to_string() };
    for _ in 0..b.count(43)? {
        let id = b.u64()?;
        let p = [b.f64()? as f32, b.f64()? as f32, b.f64()? as f32];
        let c = [b.u8()?, b.u8()?, b.u8()?].map(|v| v as f32 / 255.0);
        let _err = b.f64()?;
        let track = b.count(8)?;
        b.skip(track * 8)?;
        if !p.iter().all(|v| v.is_finite()) {
            bail!("{what}: point {id} has a non-finite position {p:?}");
        }
        m.points.positions.push(p);
        m.points.colours.push(c);
    }
    b.end()
}

/// Numbered lines of a COLMAP text file that carry data (comments and blank lines dropped).
fn data_lines(text: &str) -> impl Iterator<Item = (usize, Vec<&str>)> {
    text.lines().enumerate().filter_map(|(i, l)| {
        let t: Vec<&str> = l.split_whitespace().collect();
        (!t.is_empty() && !t[0].starts_with('#')).then_some((i + 1, t))
    })
}

fn colmap_cameras_txt(m: &mut ColmapModel, text: &str, what: &str) -> Result<()> {
    for (no, t) in data_lines(text) {
        let parse_err = || anyhow!("{what}: line {no}: expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]");
        if t.len() < 4 {
            return Err(parse_err());
        }
        let id: u32 = t[0].parse().map_err(|_| parse_err())?;
        let np = MODELS
            .iter()
            .find(|m| m.0 == t[1])
            .ok_or_else(|| anyhow!("{what}: line {no}: unknown camera model {}", t[1]))?
            .1;
        let params: Vec<f64> = t[4..].iter().map(|v| v.parse()).collect::<Result<_, _>>().map_err(|_| parse_err())?;
        if params.len() != np {
            bail!("{what}: line {no}: {} takes {np} parameters, got {}", t[1], params.len());
        }
        let (w, h) = (t[2].parse().map_err(|_| parse_err())?, t[3].parse().map_err(|_| parse_err())?);
        let at = format!("{what}: line {no}");
        let cam = colmap_camera(&at, id, t[1], w, h, params)?;
        insert_camera(m, &at, id, cam)?;
    }
    Ok(())
}

fn colmap_images_txt(m: &mut ColmapModel, text: &str, what: &str) -> Result<()> {
    // Each image takes two lines: its pose, then its 2D points (which may be empty).
    let mut expect_points = false;
    for (i, l) in text.lines().enumerate() {
        let no = i + 1;
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
        let parse_err = || anyhow!("{what}: line {no}: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME");
        if t.len() < 10 {
            return Err(parse_err());
        }
        let f: Vec<f64> = t[1..8].iter().map(|v| v.parse()).collect::<Result<_, _>>().map_err(|_| parse_err())?;
        let camera_id = t[8].parse().map_err(|_| parse_err())?;
        let image = colmap_image(
            &format!("{what}: line {no}"),
            &t[9..].join(" "),
            [f[0], f[1], f[2], f[3]],
            [f[4], f[5], f[6]],
            camera_id,
        )?;
        m.images.push(image);
        expect_points = true;
    }
    Ok(())
}

fn colmap_points_txt(m: &mut ColmapModel, text: &str, what: &str) -> Result<()> {
    for (no, t) in data_lines(text) {
        let parse_err = || anyhow!("{what}: line {no}: expected POINT3D_ID X Y Z R G B ERROR TRACK[]");
        if t.len() < 8 {
            return Err(parse_err());
        }
        let f: Vec<f32> = t[1..7].iter().map(|v| v.parse()).collect::<Result<_, _>>().map_err(|_| parse_err())?;
        if !f[..3].iter().all(|v| v.is_finite()) {
            bail!("{what}: line {no}: the point's position is not finite");
        }
        if !f[3..6].iter().all(|v| (0.0..=255.0).contains(v)) {
            bail!("{what}: line {no}: the point's colour is not in 0..255");
        }
        m.points.positions.push([f[0], f[1], f[2]]);
        m.points.colours.push([f[3] / 255.0, f[4] / 255.0, f[5] / 255.0]);
    }
    Ok(())
}

/// The intrinsics (fx, fy, cx, cy) and lens of a COLMAP camera. Models with distortion we can
/// undistort (SIMPLE_RADIAL, RADIAL, OPENCV, OPENCV_FISHEYE, SIMPLE_RADIAL_FISHEYE,
/// RADIAL_FISHEYE) come with their lens, undistorted on load ([`super::lens`]); the others are refused
/// with `what` (file, camera) and the model named.
pub fn colmap_intrinsics(cam: &ColmapCamera, what: &str) -> Result<([f32; 4], Lens)> {
    let p = &cam.params;
    let rt = |k: [f64; 4], q: [f64; 2]| Lens::RadialTangential { k, p: q };
    let (f, lens) = match cam.model.as_str() {
        "SIMPLE_PINHOLE" => ([p[0], p[0], p[1], p[2]], Lens::Pinhole),
        "PINHOLE" => ([p[0], p[1], p[2], p[3]], Lens::Pinhole),
        "SIMPLE_RADIAL" => ([p[0], p[0], p[1], p[2]], rt([p[3], 0.0, 0.0, 0.0], [0.0; 2])),
        "RADIAL" => ([p[0], p[0], p[1], p[2]], rt([p[3], p[4], 0.0, 0.0], [0.0; 2])),
        "OPENCV" => ([p[0], p[1], p[2], p[3]], rt([p[4], p[5], 0.0, 0.0], [p[6], p[7]])),
        "OPENCV_FISHEYE" => ([p[0], p[1], p[2], p[3]], Lens::Fisheye { k: [p[4], p[5], p[6], p[7]] }),
        "SIMPLE_RADIAL_FISHEYE" => ([p[0], p[0], p[1], p[2]], Lens::Fisheye { k: [p[3], 0.0, 0.0, 0.0] }),
        "RADIAL_FISHEYE" => ([p[0], p[0], p[1], p[2]], Lens::Fisheye { k: [p[3], p[4], 0.0, 0.0] }),
        other => bail!(
            "{what}: camera model {other} cannot be undistorted here (PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV and the fisheye models can); run colmap image_undistorter and train on its PINHOLE model"
        ),
    };
    let lens = if matches!(lens, Lens::RadialTangential { .. }) && lens.is_pinhole() { Lens::Pinhole } else { lens };
    Ok((f.map(|v| v as f32), lens))
}
