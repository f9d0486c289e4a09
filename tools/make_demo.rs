//! Builds the bundled demo scene (`demo/ducks6-mini`) from the shared `ducks6` scene: images
//! box-filtered down by an integer factor, instance masks subsampled (the id at each block's
//! centre, so ids stay ids), every Nth training and test view kept, the point cloud thinned.
//!
//! ```sh
//! cargo run --release --example make_demo -- ../shared/data/scenes/ducks6 demo/ducks6-mini \
//!     --factor 2 --train-every 2 --test-every 2 --points 4000
//! ```
use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};

struct Args {
    src: PathBuf,
    dst: PathBuf,
    factor: u32,
    train_every: usize,
    test_every: usize,
    points: usize,
}

fn parse() -> Result<Args> {
    let mut it = std::env::args().skip(1);
    let (Some(src), Some(dst)) = (it.next(), it.next()) else {
        bail!("usage: make_demo SRC DST [--factor F] [--train-every N] [--test-every N] [--points N]")
    };
    let mut a = Args { src: src.into(), dst: dst.into(), factor: 2, train_every: 2, test_every: 2, points: 4000 };
    while let Some(k) = it.next() {
        let v = it.next().with_context(|| format!("{k} needs a value"))?;
        match k.as_str() {
            "--factor" => a.factor = v.parse()?,
            "--train-every" => a.train_every = v.parse()?,
            "--test-every" => a.test_every = v.parse()?,
            "--points" => a.points = v.parse()?,
            _ => bail!("unknown option {k}"),
        }
    }
    if a.factor == 0 || a.train_every == 0 || a.test_every == 0 {
        bail!("--factor, --train-every and --test-every must be positive");
    }
    Ok(a)
}

fn split(a: &Args, name: &str, every: usize) -> Result<()> {
    let path = a.src.join(format!("transforms_{name}.json"));
    let text = std::fs::read_to_string(&path).with_context(|| format!("{}: cannot read", path.display()))?;
    let mut doc: serde_json::Value = serde_json::from_str(&text)?;
    let f = a.factor as f64;
    for key in ["fl_x", "fl_y", "cx", "cy"] {
        if let Some(v) = doc[key].as_f64() {
            doc[key] = (v / f).into();
        }
    }
    for key in ["w", "h"] {
        if let Some(v) = doc[key].as_u64() {
            doc[key] = (v / a.factor as u64).into();
        }
    }
    let frames: Vec<serde_json::Value> =
        doc["frames"].as_array().context("no frames")?.iter().step_by(every).cloned().collect();
    for dir in [a.dst.join(name), a.dst.join("masks").join(name)] {
        std::fs::create_dir_all(&dir)?;
    }
    for fr in &frames {
        let file = format!("{}.png", fr["file_path"].as_str().context("file_path")?);
        let img = image::open(a.src.join(&file)).with_context(|| file.clone())?.to_rgb8();
        let (w, h) = (img.width() / a.factor, img.height() / a.factor);
        let small = image::imageops::resize(&img, w, h, image::imageops::FilterType::Triangle);
        small.save(a.dst.join(&file))?;
        let stem = Path::new(&file).file_name().context("name")?;
        let mask = image::open(a.src.join("masks").join(name).join(stem))?.to_luma16();
        let c = a.factor / 2;
        let small = image::ImageBuffer::from_fn(w, h, |x, y| *mask.get_pixel(x * a.factor + c, y * a.factor + c));
        image::DynamicImage::ImageLuma16(small).save(a.dst.join("masks").join(name).join(stem))?;
    }
    doc["frames"] = frames.into();
    std::fs::write(a.dst.join(format!("transforms_{name}.json")), serde_json::to_string_pretty(&doc)?)?;
    Ok(())
}

fn main() -> Result<()> {
    let a = parse()?;
    std::fs::create_dir_all(&a.dst)?;
    split(&a, "train", a.train_every)?;
    split(&a, "test", a.test_every)?;
    std::fs::copy(a.src.join("instances.json"), a.dst.join("instances.json"))?;
    let pc = instgs_vk::dataset::read_points_ply(&a.src.join("points3d.ply"))?;
    let step = pc.positions.len().div_ceil(a.points.max(1)).max(1);
    let mut ply = String::new();
    let kept: Vec<usize> = (0..pc.positions.len()).step_by(step).collect();
    ply += &format!(
        "ply\nformat ascii 1.0\nelement vertex {}\nproperty float x\nproperty float y\nproperty float z\n\
         property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n",
        kept.len()
    );
    for i in kept {
        let [x, y, z] = pc.positions[i];
        let [r, g, b] = pc.colours[i].map(|c| (c * 255.0).round() as u8);
        ply += &format!("{x} {y} {z} {r} {g} {b}\n");
    }
    std::fs::write(a.dst.join("points3d.ply"), ply)?;
    Ok(())
}
