//! PlayCanvas SOG (`meta.json` and WebP images): versions 1 and 2 read, version 2 written.
use std::path::{Path, PathBuf};

use anyhow::{anyhow, bail, Context, Result};

use crate::formats::quant::{largest_component, opacity_logit, unorm8};
use crate::math::sigmoid;
use crate::model::scene::Scene;

#[derive(serde::Deserialize)]
struct SogMeans {
    mins: [f32; 3],
    maxs: [f32; 3],
    files: [String; 2],
    /// Version 1: [count, 3].
    shape: Option<[usize; 2]>,
}

/// An attribute's table: version 2 a 256-entry `codebook`, version 1 per-channel `mins` and
/// `maxs` (bytes lerped between them).
#[derive(serde::Deserialize)]
struct SogTable {
    codebook: Option<Vec<f32>>,
    mins: Option<Vec<f32>>,
    maxs: Option<Vec<f32>>,
    files: Vec<String>,
}

#[derive(serde::Deserialize)]
struct SogFiles {
    files: Vec<String>,
}

/// Version 2: `count`, `bands`, `codebook`; version 1: scalar `mins`/`maxs`, bands from the
/// centroids image's width.
#[derive(serde::Deserialize)]
struct SogShN {
    count: Option<usize>,
    bands: Option<u32>,
    codebook: Option<Vec<f32>>,
    mins: Option<f32>,
    maxs: Option<f32>,
    files: [String; 2],
}

#[derive(serde::Deserialize)]
struct SogMeta {
    version: Option<u32>,
    count: Option<usize>,
    means: SogMeans,
    scales: SogTable,
    quats: SogFiles,
    sh0: SogTable,
    #[serde(rename = "shN")]
    sh_n: Option<SogShN>,
}

/// Decodes a byte of channel `c`: a codebook entry (version 2) or a lerp (version 1).
enum Lookup {
    Codebook(Vec<f32>),
    Lerp(Vec<f32>, Vec<f32>),
}

impl Lookup {
    fn new(what: &str, name: &str, t: &SogTable, v1: bool, channels: usize) -> Result<Lookup> {
        if v1 {
            match (&t.mins, &t.maxs) {
                (Some(lo), Some(hi)) if lo.len() >= channels && hi.len() >= channels => {
                    Ok(Lookup::Lerp(lo.clone(), hi.clone()))
                }
                _ => bail!("{what}: \"{name}\" needs {channels} mins and maxs (SOG version 1)"),
            }
        } else {
            match &t.codebook {
                Some(c) if c.len() == 256 => Ok(Lookup::Codebook(c.clone())),
                _ => bail!("{what}: \"{name}\" needs a 256-entry codebook (SOG version 2)"),
            }
        }
    }

    fn get(&self, c: usize, b: u8) -> f32 {
        match self {
            Lookup::Codebook(book) => book[b as usize],
            Lookup::Lerp(lo, hi) => lo[c] + (hi[c] - lo[c]) * (b as f32 / 255.0),
        }
    }
}

/// An RGBA image decoded from a SOG WebP file `name` (bytes from `load`): (width, height, bytes).
/// Its size is read from the header first and its RGBA texels checked against the memory
/// budget ([`crate::limits`]) before anything is decoded.
fn sog_image(load: &mut Loader, name: &str, count: usize) -> Result<(usize, usize, Vec<u8>)> {
    let (what, bytes) = load(name)?;
    let (w, h) = image::ImageReader::with_format(std::io::Cursor::new(&bytes), image::ImageFormat::WebP)
        .into_dimensions()
        .map_err(|e| anyhow!("{what}: not a WebP image: {e}"))?;
    crate::limits::check_bytes(&what, &format!("its {w}×{h} texels"), 4 * w as u64 * h as u64)?;
    let img = image::load_from_memory_with_format(&bytes, image::ImageFormat::WebP)
        .map_err(|e| anyhow!("{what}: not a WebP image: {e}"))?
        .to_rgba8();
    let (w, h) = (img.width() as usize, img.height() as usize);
    if w * h < count {
        bail!("{what}: {w}×{h} texels cannot hold {count} Gaussians");
    }
    Ok((w, h, img.into_raw()))
}

/// Reads the file a SOG's `meta.json` names: (its name for messages, its bytes).
type Loader<'a> = dyn FnMut(&str) -> Result<(String, Vec<u8>)> + 'a;

/// Reads a SOG scene, version 2 or 1: `meta.json` (or its folder) and the WebP images it
/// names (splat-transform's layouts; version 1 lerps bytes between per-channel bounds where
/// version 2 has codebooks, and stores the opacity logit itself).
pub fn read_sog(path: &Path) -> Result<Scene> {
    let meta_path: PathBuf = if path.is_dir() { path.join("meta.json") } else { path.to_path_buf() };
    let what = meta_path.display().to_string();
    let bytes = std::fs::read(&meta_path).with_context(|| format!("{what}: cannot read"))?;
    if bytes.starts_with(b"PK\x03\x04") {
        return sog_from_bundle(&bytes, &what);
    }
    let text = String::from_utf8(bytes).map_err(|_| anyhow!("{what}: cannot read: not UTF-8 text"))?;
    sog_from_meta(&text, &what, &mut |name| {
        // Only a file beside meta.json (crate::limits::confined), an image at most as large as a
        // bundle's entry may be.
        let path = crate::limits::confined(&meta_path, "a file it names", name)?;
        let bytes = crate::limits::read_limited(&path, &what, &format!("{name:?}"), MAX_BUNDLE_ENTRY, true)?;
        Ok((path.display().to_string(), bytes))
    })
}

/// Whether `path` is a zip archive holding a `meta.json` (a `.sog` bundle).
pub fn is_sog_bundle(path: &Path) -> bool {
    std::fs::File::open(path)
        .ok()
        .and_then(|f| zip::ZipArchive::new(std::io::BufReader::new(f)).ok())
        .is_some_and(|z| z.index_for_name("meta.json").is_some())
}

/// A SOG scene from the bytes of a `.sog` bundle (`what` names it in errors): a zip archive of
/// `meta.json` and the images it names, stored or deflated (splat-transform 3.x's single-file
/// output).
pub fn sog_from_bundle(bytes: &[u8], what: &str) -> Result<Scene> {
    let mut zip = zip::ZipArchive::new(std::io::Cursor::new(bytes))
        .map_err(|e| anyhow!("{what}: not a readable zip archive: {e}"))?;
    let mut entry = |name: &str| -> Result<Vec<u8>> {
        let mut f = zip.by_name(name).map_err(|e| anyhow!("{what}: no {name} in the bundle ({e})"))?;
        // The size the archive declares bounds the read (a bomb is refused, not expanded).
        if f.size() > MAX_BUNDLE_ENTRY {
            bail!("{what}: {name} would expand to {} bytes, more than {MAX_BUNDLE_ENTRY}", f.size());
        }
        let mut out = Vec::with_capacity(f.size().min(1 << 24) as usize);
        std::io::Read::read_to_end(&mut std::io::Read::take(&mut f, MAX_BUNDLE_ENTRY + 1), &mut out)
            .map_err(|e| anyhow!("{what}: {name}: cannot read from the bundle: {e}"))?;
        if out.len() as u64 > MAX_BUNDLE_ENTRY {
            bail!("{what}: {name} expands past {MAX_BUNDLE_ENTRY} bytes");
        }
        Ok(out)
    };
    let meta = entry("meta.json")?;
    let text = String::from_utf8(meta).map_err(|_| anyhow!("{what}: meta.json is not UTF-8 text"))?;
    sog_from_meta(&text, &format!("{what}: meta.json"), &mut |name| Ok((format!("{what}: {name}"), entry(name)?)))
}

/// The largest file a `.sog` bundle may expand to (an image of 16 384² RGBA texels).
const MAX_BUNDLE_ENTRY: u64 = 1 << 30;

/// [`read_sog`] from the text of `meta.json` (`what` names it in errors) and `load`, which
/// returns the file a name in it names.
pub fn sog_from_meta(text: &str, what: &str, load: &mut Loader) -> Result<Scene> {
    let meta: SogMeta = serde_json::from_str(text).map_err(|e| anyhow!("{what}: not a SOG meta.json: {e}"))?;
    let v1 = match meta.version {
        Some(2) => false,
        None => true,
        Some(v) => bail!("{what}: SOG version {v} is not read (versions 1 and 2 are)"),
    };
    let n = if v1 { meta.means.shape.map(|s| s[0]) } else { meta.count }
        .ok_or_else(|| anyhow!("{what}: no Gaussian count (\"count\", or version 1's \"means.shape\")"))?;
    if n == 0 {
        bail!("{what}: the SOG holds no Gaussians");
    }
    let scale_of = Lookup::new(what, "scales", &meta.scales, v1, 3)?;
    let sh0_of = Lookup::new(what, "sh0", &meta.sh0, v1, if v1 { 4 } else { 3 })?;
    let one =
        |c: &SogTable, name: &str| c.files.first().cloned().ok_or_else(|| anyhow!("{what}: \"{name}\" names no file"));
    // Every per-Gaussian image of one scene has one size (texel i is Gaussian i in all of them).
    let mut size = None;
    let mut per_gaussian = |load: &mut Loader, name: &str| -> Result<Vec<u8>> {
        let (w, h, bytes) = sog_image(load, name, n)?;
        match size {
            None => size = Some((w, h, name.to_string())),
            Some((w0, h0, ref first)) if (w0, h0) != (w, h) => {
                bail!("{what}: {name} is {w}×{h} texels, {first} {w0}×{h0}: the images of one scene share one size")
            }
            Some(_) => {}
        }
        Ok(bytes)
    };
    let lo = per_gaussian(load, &meta.means.files[0])?;
    let hi = per_gaussian(load, &meta.means.files[1])?;
    let quat_file = meta.quats.files.first().ok_or_else(|| anyhow!("{what}: \"quats\" names no file"))?;
    let quats = per_gaussian(load, quat_file)?;
    let scales = per_gaussian(load, &one(&meta.scales, "scales")?)?;
    let sh0 = per_gaussian(load, &one(&meta.sh0, "sh0")?)?;
    // The SH palette: (coefficients, centroids image width, its bytes, labels, entries, lookup).
    let mut palette = None;
    let mut degree = 0;
    if let Some(sh) = &meta.sh_n {
        let centroids_path = &sh.files[0];
        let (cw, ch, centroids) = sog_image(load, &sh.files[0], 0)?;
        let bands = if v1 {
            match cw {
                192 => 1,
                512 => 2,
                960 => 3,
                _ => {
                    bail!("{what}: {centroids_path}: {cw} texels wide; SOG version 1 palettes are 192, 512 or 960")
                }
            }
        } else {
            sh.bands.unwrap_or(0)
        };
        if bands > 3 {
            bail!("{what}: shN with {bands} bands is not supported (1..3)");
        }
        if bands > 0 {
            let coeffs = ((bands + 1) * (bands + 1) - 1) as usize;
            if cw != 64 * coeffs {
                bail!("{what}: {centroids_path}: {cw} texels wide; {bands} bands need {}", 64 * coeffs);
            }
            let (count, lookup) = if v1 {
                let (Some(a), Some(b)) = (sh.mins, sh.maxs) else {
                    bail!("{what}: \"shN\" needs mins and maxs (SOG version 1)")
                };
                (ch * 64, Lookup::Lerp(vec![a; 3], vec![b; 3]))
            } else {
                match (&sh.codebook, sh.count) {
                    (Some(c), Some(count)) if c.len() == 256 => (count, Lookup::Codebook(c.clone())),
                    _ => bail!("{what}: \"shN\" needs a count and a 256-entry codebook (SOG version 2)"),
                }
            };
            if count > ch * 64 {
                bail!("{what}: shN count {count} exceeds its centroids image ({} entries)", ch * 64);
            }
            let labels = per_gaussian(load, &sh.files[1])?;
            degree = bands;
            palette = Some((coeffs, cw, centroids, labels, count, lookup));
        }
    }
    let m = &meta.means;
    let mut s = Scene { sh_degree: degree, ..Default::default() };
    let unlog = |v: f32| v.signum() * (v.abs().exp() - 1.0);
    for i in 0..n {
        let o = i * 4;
        s.means.push(std::array::from_fn(|a| {
            // The format's lerp(mins, maxs, q), whatever the bounds' order.
            let q = (lo[o + a] as u32 | (hi[o + a] as u32) << 8) as f32 / 65535.0;
            unlog(m.mins[a] + (m.maxs[a] - m.mins[a]) * q)
        }));
        let tag = quats[o + 3];
        if !(252..=255).contains(&tag) {
            bail!("{what}: Gaussian {i}'s rotation tag {tag} is not 252-255");
        }
        let largest = (tag - 252) as usize;
        let abc = [0, 1, 2].map(|k| (quats[o + k] as f32 / 255.0 * 2.0 - 1.0) * std::f32::consts::FRAC_1_SQRT_2);
        let mut q = [0.0f32; 4];
        let mut k = 0;
        for (j, v) in q.iter_mut().enumerate() {
            if j != largest {
                *v = abc[k];
                k += 1;
            }
        }
        q[largest] = (1.0 - abc.iter().map(|v| v * v).sum::<f32>()).max(0.0).sqrt();
        s.quats.push(q);
        s.scales.push(std::array::from_fn(|a| scale_of.get(a, scales[o + a])));
        s.opacities.push(if v1 {
            // Version 1 stores the logit itself between its bounds.
            sh0_of.get(3, sh0[o + 3])
        } else {
            opacity_logit(sh0[o + 3] as f32 / 255.0)
        });
        for c in 0..3 {
            s.sh.push(sh0_of.get(c, sh0[o + c]));
        }
        if let Some((coeffs, cw, centroids, labels, count, lookup)) = &palette {
            let label = labels[o] as usize | (labels[o + 1] as usize) << 8;
            if label >= *count {
                bail!("{what}: Gaussian {i}'s SH palette label {label} is not below its count {count}");
            }
            let (row, col) = (label / 64, (label % 64) * coeffs);
            for j in 0..*coeffs {
                let t = (row * cw + col + j) * 4;
                for c in 0..3 {
                    s.sh.push(lookup.get(c, centroids[t + c]));
                }
            }
        }
    }
    Ok(s)
}

/// 1D k-means (Lloyd) of `values` into at most `k` centres, ascending; `weights` (one per
/// value, positive) count a value that many times (none: each once).
fn codebook_1d(values: &[f32], weights: Option<&[f32]>, k: usize) -> Vec<f32> {
    let mut v: Vec<(f32, f64)> = match weights {
        Some(w) => values.iter().zip(w).map(|(&x, &w)| (x, w as f64)).collect(),
        None => values.iter().map(|&x| (x, 1.0)).collect(),
    };
    v.sort_by(|a, b| a.0.total_cmp(&b.0));
    let n = v.len();
    if n == 0 {
        return vec![0.0; k];
    }
    // Half the starts at quantiles of the weight (where the values are), half evenly over the
    // range (so the rare extremes — the largest splats, the brightest colours — keep entries of
    // their own).
    let mut cumulative = Vec::with_capacity(n);
    let mut total = 0.0f64;
    for &(_, w) in &v {
        total += w;
        cumulative.push(total);
    }
    let (lo, hi) = (v[0].0, v[n - 1].0);
    let mut centres: Vec<f32> = (0..k)
        .map(|i| {
            let t = (i / 2) as f64 / (k / 2).max(1) as f64 + 0.5 / k as f64;
            if i % 2 == 0 {
                v[cumulative.partition_point(|&c| c <= t * total).min(n - 1)].0
            } else {
                // In f64: the span of values near ±f32::MAX overflows f32.
                (lo as f64 + (hi as f64 - lo as f64) * t) as f32
            }
        })
        .collect();
    centres.sort_by(f32::total_cmp);
    for _ in 0..10 {
        centres.dedup();
        // Sorted values: each centre's members are a run between the midpoints.
        let mut sums = vec![(0.0f64, 0.0f64); centres.len()];
        let mut c = 0;
        for &(x, w) in &v {
            while c + 1 < centres.len() && x > 0.5 * centres[c] + 0.5 * centres[c + 1] {
                c += 1;
            }
            sums[c].0 += w * x as f64;
            sums[c].1 += w;
        }
        for (centre, (s, m)) in centres.iter_mut().zip(&sums) {
            if *m > 0.0 {
                *centre = (*s / *m) as f32;
            }
        }
        centres.sort_by(f32::total_cmp);
    }
    centres.resize(k, *centres.last().unwrap_or(&0.0));
    centres
}

/// The index of the codebook entry nearest to `x` (the codebook ascending).
fn nearest(codebook: &[f32], x: f32) -> u8 {
    let i = codebook.partition_point(|&c| c < x);
    let best = match i {
        0 => 0,
        i if i >= codebook.len() => codebook.len() - 1,
        i => {
            if (x - codebook[i - 1]).abs() <= (codebook[i] - x).abs() {
                i - 1
            } else {
                i
            }
        }
    };
    best as u8
}

/// Entries of the SH palette (k-means centres of the Gaussians' shN vectors) at most.
pub const SOG_PALETTE: usize = 1024;

fn write_webp(path: &Path, w: usize, h: usize, rgba: &[u8]) -> Result<()> {
    let mut bytes = Vec::new();
    image::codecs::webp::WebPEncoder::new_lossless(&mut bytes)
        .encode(rgba, w as u32, h as u32, image::ExtendedColorType::Rgba8)
        .map_err(|e| anyhow!("{}: WebP: {e}", path.display()))?;
    crate::util::write_atomic(path, |f| std::io::Write::write_all(f, &bytes))
}

/// `scene` as SOG version 2: `meta.json` and lossless WebP images in the folder of `meta`
/// (created). Positions 16-bit in log space (splat-transform's sign(x)·ln(|x| + 1)), rotations
/// smallest-three 8-bit, scales and sh0 through 256-entry codebooks (1D k-means), opacity 8-bit,
/// SH bands as a palette of at most [`SOG_PALETTE`] k-means centres (10 Lloyd iterations) whose
/// coefficients go through a third codebook.
/// The files are written into a temporary sibling folder first and moved in only when all were
/// written (`meta.json` last): a failure leaves an existing SOG folder as it was.
pub fn write_sog(scene: &Scene, meta: &Path) -> Result<()> {
    scene.validate(&format!("{}: not written", meta.display()))?;
    let dir = meta.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
    let name = meta.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_else(|| "meta.json".into());
    crate::util::write_dir_atomic(dir, Some(&name), |tmp| write_sog_files(scene, &tmp.join(&name), None))
        .with_context(|| format!("{}: not written", meta.display()))
}

/// `scene` as one `.sog` file: [`write_sog`]'s `meta.json` and images in a zip archive (stored:
/// the WebP images are compressed already), written atomically.
pub fn write_sog_bundle(scene: &Scene, out: &Path) -> Result<()> {
    scene.validate(&format!("{}: not written", out.display()))?;
    let name = out.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    let parent = out.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
    let tmp = parent.join(format!(".{name}.{}.files.tmp", std::process::id()));
    let bytes = bundle_in(scene, &tmp, None).with_context(|| format!("{}: cannot write the bundle", out.display()))?;
    crate::util::write_atomic(out, |f| std::io::Write::write_all(f, &bytes))
}

/// The bytes of [`write_sog_bundle`]'s file for `scene` (its images made in a scratch folder
/// of the system's temporary directory, removed after). `weights` (one per Gaussian, positive:
/// how many times it is drawn, as a template's Gaussian is once per instance) weigh the
/// codebooks' and the SH palette's k-means; none: each Gaussian once.
pub fn bundle_bytes(scene: &Scene, weights: Option<&[f32]>) -> Result<Vec<u8>> {
    scene.validate("the SOG bundle")?;
    if let Some(w) = weights {
        if w.len() != scene.len() || w.iter().any(|w| !(w.is_finite() && *w > 0.0)) {
            bail!("the SOG bundle: {} weights for {} Gaussians, each must be positive", w.len(), scene.len());
        }
    }
    static NEXT: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
    let n = NEXT.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let tmp = std::env::temp_dir().join(format!("instgs-sog-{}-{n}.tmp", std::process::id()));
    bundle_in(scene, &tmp, weights).context("cannot make a SOG bundle")
}

/// The bundle's bytes, its files written into `tmp` first (removed after).
fn bundle_in(scene: &Scene, tmp: &Path, weights: Option<&[f32]>) -> Result<Vec<u8>> {
    let result = (|| -> Result<Vec<u8>> {
        std::fs::create_dir_all(tmp)?;
        write_sog_files(scene, &tmp.join("meta.json"), weights)?;
        let mut names: Vec<String> = std::fs::read_dir(tmp)?
            .map(|e| e.map(|e| e.file_name().to_string_lossy().into_owned()))
            .collect::<std::io::Result<_>>()?;
        // meta.json first, as splat-transform writes it; the images in name order.
        names.sort_by_key(|n| (n != "meta.json", n.clone()));
        let mut zip = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
        let options = zip::write::SimpleFileOptions::default().compression_method(zip::CompressionMethod::Stored);
        for name in &names {
            zip.start_file(name.as_str(), options)?;
            std::io::Write::write_all(&mut zip, &std::fs::read(tmp.join(name))?)?;
        }
        Ok(zip.finish()?.into_inner())
    })();
    let _ = std::fs::remove_dir_all(tmp);
    result
}

/// [`write_sog`]'s files, written into `meta`'s folder; `weights` as [`bundle_bytes`]'s.
fn write_sog_files(scene: &Scene, meta: &Path, weights: Option<&[f32]>) -> Result<()> {
    let dir = meta.parent().expect("a folder");
    let n = scene.len();
    let coeffs = scene.sh_coeffs();
    let w = ((n as f64).sqrt().ceil() as usize).div_ceil(4) * 4;
    let h = n.div_ceil(w);
    let image = || vec![0u8; w * h * 4];
    let log = |x: f32| x.signum() * (x.abs() + 1.0).ln();
    // Past this the reader's exp of the lerped log (within its rounding of the bounds) overflows.
    const MAX_POSITION: f32 = 1e38;
    if let Some((i, m)) = scene.means.iter().enumerate().find(|(_, m)| m.iter().any(|v| v.abs() > MAX_POSITION)) {
        bail!("Gaussian {i}'s position {m:?} is past ±{MAX_POSITION:e}, which SOG's log-space positions cannot hold");
    }
    let mut mins = [f32::MAX; 3];
    let mut maxs = [f32::MIN; 3];
    for m in &scene.means {
        for a in 0..3 {
            mins[a] = mins[a].min(log(m[a]));
            maxs[a] = maxs[a].max(log(m[a]));
        }
    }
    let (mut lo, mut hi, mut quats, mut scales, mut sh0) = (image(), image(), image(), image(), image());
    // Three values a Gaussian: its weight three times.
    let weights3: Option<Vec<f32>> = weights.map(|w| w.iter().flat_map(|&w| [w; 3]).collect());
    let scale_book = codebook_1d(&scene.scales.iter().flatten().copied().collect::<Vec<_>>(), weights3.as_deref(), 256);
    let dc: Vec<f32> = (0..n).flat_map(|i| scene.sh[i * coeffs * 3..i * coeffs * 3 + 3].to_vec()).collect();
    let sh0_book = codebook_1d(&dc, weights3.as_deref(), 256);
    for i in 0..n {
        let o = i * 4;
        for a in 0..3 {
            let range = if maxs[a] > mins[a] { maxs[a] - mins[a] } else { 1.0 };
            let q = (((log(scene.means[i][a]) - mins[a]) / range * 65535.0).round().clamp(0.0, 65535.0)) as u32;
            lo[o + a] = (q & 255) as u8;
            hi[o + a] = (q >> 8) as u8;
            scales[o + a] = nearest(&scale_book, scene.scales[i][a]);
            sh0[o + a] = nearest(&sh0_book, dc[i * 3 + a]);
        }
        lo[o + 3] = 255;
        hi[o + 3] = 255;
        scales[o + 3] = 255;
        sh0[o + 3] = unorm8(sigmoid(scene.opacities[i]));
        let (largest, q) = largest_component(scene.quats[i]);
        let mut k = 0;
        for (j, v) in q.iter().enumerate() {
            if j != largest {
                quats[o + k] = unorm8((v * std::f32::consts::SQRT_2 + 1.0) * 0.5);
                k += 1;
            }
        }
        quats[o + 3] = 252 + largest as u8;
    }
    let names = ["means_l.webp", "means_u.webp", "quats.webp", "scales.webp", "sh0.webp"];
    for (name, img) in names.iter().zip([&lo, &hi, &quats, &scales, &sh0]) {
        write_webp(&dir.join(name), w, h, img)?;
    }
    let mut doc = serde_json::json!({
        "version": 2,
        "asset": {"generator": "instgs-vk"},
        "count": n,
        "means": {"mins": mins, "maxs": maxs, "files": [names[0], names[1]]},
        "scales": {"codebook": scale_book, "files": [names[3]]},
        "quats": {"files": [names[2]]},
        "sh0": {"codebook": sh0_book, "files": [names[4]]},
    });
    if coeffs > 1 {
        let rest = (coeffs - 1) * 3;
        let vectors: Vec<&[f32]> = (0..n).map(|i| &scene.sh[i * coeffs * 3 + 3..(i + 1) * coeffs * 3]).collect();
        let (centres, labels) = palette(&vectors, weights, rest, SOG_PALETTE.min(n));
        let book = codebook_1d(&centres, None, 256);
        let count = centres.len() / rest;
        let (cw, ch) = (64 * (coeffs - 1), count.div_ceil(64));
        let mut cimg = vec![0u8; cw * ch * 4];
        for c in 0..count {
            for j in 0..coeffs - 1 {
                let t = ((c / 64) * cw + (c % 64) * (coeffs - 1) + j) * 4;
                for ch in 0..3 {
                    // Centres are stored coefficient-major then RGB, as the Gaussians' sh.
                    cimg[t + ch] = nearest(&book, centres[c * rest + j * 3 + ch]);
                }
                cimg[t + 3] = 255;
            }
        }
        let mut limg = image();
        for (i, &l) in labels.iter().enumerate() {
            limg[i * 4] = (l & 255) as u8;
            limg[i * 4 + 1] = (l >> 8) as u8;
            limg[i * 4 + 3] = 255;
        }
        write_webp(&dir.join("shN_centroids.webp"), cw, ch, &cimg)?;
        write_webp(&dir.join("shN_labels.webp"), w, h, &limg)?;
        doc["shN"] = serde_json::json!({
            "count": count, "bands": scene.sh_degree, "codebook": book,
            "files": ["shN_centroids.webp", "shN_labels.webp"],
        });
    }
    // serde_json writes a value that is not finite as null, which no reader takes. The codebooks
    // keep values near f32::MAX finite (their span taken in f64, midpoints halved before the
    // sum); should any entry still not be finite, the file is refused rather than written.
    fn non_finite(v: &serde_json::Value) -> bool {
        match v {
            serde_json::Value::Null => true,
            serde_json::Value::Array(a) => a.iter().any(non_finite),
            serde_json::Value::Object(o) => o.values().any(non_finite),
            _ => false,
        }
    }
    if non_finite(&doc) {
        bail!("the scene's values overflow SOG's codebooks (a centre or range is not finite)");
    }
    let text = serde_json::to_string(&doc)?;
    crate::util::write_atomic(meta, |f| std::io::Write::write_all(f, text.as_bytes()))
}

/// k-means of `vectors` (each `dim` long) into `k` centres, each vector counted `weights[i]`
/// times (none: once): starts evenly spaced in the cumulative weight, 10 Lloyd iterations,
/// brute-force assignment. Returns the centres (flat) and each vector's label.
fn palette(vectors: &[&[f32]], weights: Option<&[f32]>, dim: usize, k: usize) -> (Vec<f32>, Vec<u32>) {
    let n = vectors.len();
    let weight = |i: usize| weights.map_or(1.0, |w| w[i] as f64);
    let mut cumulative = Vec::with_capacity(n);
    let mut total = 0.0f64;
    for i in 0..n {
        total += weight(i);
        cumulative.push(total);
    }
    let mut centres: Vec<f32> = (0..k)
        .flat_map(|c| {
            let i = cumulative.partition_point(|&w| w <= c as f64 * total / k as f64).min(n - 1);
            vectors[i].to_vec()
        })
        .collect();
    let mut labels = vec![0u32; n];
    for _ in 0..10 {
        for (i, v) in vectors.iter().enumerate() {
            let mut best = (f32::MAX, 0);
            for c in 0..k {
                let d: f32 = centres[c * dim..(c + 1) * dim].iter().zip(*v).map(|(a, b)| (a - b) * (a - b)).sum();
                if d < best.0 {
                    best = (d, c);
                }
            }
            labels[i] = best.1 as u32;
        }
        let mut sums = vec![0.0f64; k * dim];
        let mut counts = vec![0.0f64; k];
        for (i, (v, &l)) in vectors.iter().zip(&labels).enumerate() {
            let w = weight(i);
            counts[l as usize] += w;
            for (s, x) in sums[l as usize * dim..(l as usize + 1) * dim].iter_mut().zip(*v) {
                *s += w * *x as f64;
            }
        }
        for c in 0..k {
            if counts[c] > 0.0 {
                for d in 0..dim {
                    centres[c * dim + d] = (sums[c * dim + d] / counts[c]) as f32;
                }
            }
        }
    }
    (centres, labels)
}
