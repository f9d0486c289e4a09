//! Small helpers: atomic file writes and image output.
use std::io::Write;
use std::path::Path;

use anyhow::{Context, Result};

/// Writes a file through a temporary sibling that is renamed into place, so readers never see
/// a partial file.
pub fn write_atomic(path: &Path, f: impl FnOnce(&mut std::fs::File) -> std::io::Result<()>) -> Result<()> {
    let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    let tmp = path.with_file_name(format!(".{name}.{}.tmp", std::process::id()));
    let result = (|| {
        let mut file = std::fs::File::create(&tmp)?;
        f(&mut file)?;
        file.flush()?;
        file.sync_all()?;
        std::fs::rename(&tmp, path)
    })();
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    result.with_context(|| format!("{}: cannot write", path.display()))
}

/// Writes a folder's files through a temporary sibling folder: `f` writes them into the folder
/// it is given; only when it succeeds are they moved into `dir` (created if needed; files of
/// `dir` that `f` did not write stay, those it wrote replace theirs, `last` — a file that marks
/// the folder complete, such as SOG's meta.json — moved last). On failure nothing in `dir`
/// changes, and a `dir` this call would have created does not appear.
pub fn write_dir_atomic(dir: &Path, last: Option<&str>, f: impl FnOnce(&Path) -> Result<()>) -> Result<()> {
    let name = dir.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_else(|| "out".into());
    let parent = dir.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
    std::fs::create_dir_all(parent).with_context(|| format!("{}: cannot create folder", parent.display()))?;
    let tmp = parent.join(format!(".{name}.{}.tmp", std::process::id()));
    let _ = std::fs::remove_dir_all(&tmp);
    std::fs::create_dir(&tmp).with_context(|| format!("{}: cannot create folder", tmp.display()))?;
    let result = f(&tmp).and_then(|()| {
        if !dir.exists() {
            return std::fs::rename(&tmp, dir).with_context(|| format!("{}: cannot write", dir.display()));
        }
        let mut files: Vec<std::path::PathBuf> = Vec::new();
        for e in std::fs::read_dir(&tmp)? {
            files.push(e?.path());
        }
        files.sort_by_key(|p| last.is_some_and(|l| p.file_name().is_some_and(|n| n == l)));
        for p in files {
            let to = dir.join(p.file_name().expect("a file name"));
            std::fs::rename(&p, &to).with_context(|| format!("{}: cannot write", to.display()))?;
        }
        Ok(())
    });
    let _ = std::fs::remove_dir_all(&tmp);
    result
}

/// A run folder this run creates ([`NewFolder::create`]): if the run fails before the folder
/// holds anything worth resuming (a finished stage, a training checkpoint), dropping the guard
/// removes it again, so an error leaves no empty or half-written folder behind.
pub struct NewFolder {
    path: std::path::PathBuf,
    keep: bool,
}

impl NewFolder {
    /// Creates `path` (and its parents); None when it existed already (then nothing is removed).
    pub fn create(path: &Path) -> Result<Option<NewFolder>> {
        let fresh = !path.exists();
        std::fs::create_dir_all(path).with_context(|| format!("{}: cannot create", path.display()))?;
        Ok(fresh.then(|| NewFolder { path: path.to_path_buf(), keep: false }))
    }

    /// The folder stays whatever happens next.
    pub fn keep(&mut self) {
        self.keep = true;
    }
}

impl Drop for NewFolder {
    fn drop(&mut self) {
        fn has_checkpoint(d: &Path) -> bool {
            std::fs::read_dir(d).into_iter().flatten().flatten().any(|e| {
                let p = e.path();
                p.file_name().is_some_and(|n| n == "checkpoint.bin") || (p.is_dir() && has_checkpoint(&p))
            })
        }
        if !self.keep && !has_checkpoint(&self.path) {
            let _ = std::fs::remove_dir_all(&self.path);
        }
    }
}

/// Writes `v` as JSON, atomically.
pub fn write_json(path: &Path, v: &serde_json::Value, pretty: bool) -> Result<()> {
    let text = if pretty { serde_json::to_string_pretty(v)? } else { serde_json::to_string(v)? };
    write_atomic(path, |f| f.write_all(text.as_bytes()))
}

/// Saves RGBA float pixels (row-major, rgb used, clamped to [0, 1]) as an 8-bit RGB PNG.
pub fn save_png(path: &Path, width: u32, height: u32, rgba: &[[f32; 4]]) -> Result<()> {
    let mut bytes = Vec::with_capacity(rgba.len() * 3);
    for p in rgba {
        for c in &p[..3] {
            bytes.push((c.clamp(0.0, 1.0) * 255.0).round() as u8);
        }
    }
    let mut png = Vec::new();
    image::codecs::png::PngEncoder::new(&mut png)
        .write_image(&bytes, width, height, image::ExtendedColorType::Rgb8)
        .with_context(|| format!("{}: PNG encoding failed", path.display()))?;
    write_atomic(path, |f| f.write_all(&png))
}

use image::ImageEncoder as _;

/// PSNR in dB between two RGB images given as RGBA floats (alpha ignored), values in [0, 1].
pub fn psnr(a: &[[f32; 4]], b: &[[f32; 4]]) -> f64 {
    psnr_where(a, b, |_| true).unwrap_or(f64::INFINITY)
}

/// PSNR in dB over the pixels `keep` selects (by index); None when it selects none.
pub fn psnr_where(a: &[[f32; 4]], b: &[[f32; 4]], keep: impl Fn(usize) -> bool) -> Option<f64> {
    let (mut se, mut n) = (0.0f64, 0usize);
    for (p, q) in a.iter().zip(b).enumerate().filter(|(i, _)| keep(*i)).map(|(_, pq)| pq) {
        for c in 0..3 {
            let d = (p[c].clamp(0.0, 1.0) - q[c].clamp(0.0, 1.0)) as f64;
            se += d * d;
        }
        n += 1;
    }
    if n == 0 {
        return None;
    }
    let mse = se / (n * 3) as f64;
    Some(if mse == 0.0 { f64::INFINITY } else { -10.0 * mse.log10() })
}

/// `over`'s values replace `base`'s, recursively through JSON objects; keys only in `base` stay
/// (saved configurations and settings read over today's defaults).
pub fn json_overlay(base: &mut serde_json::Value, over: &serde_json::Value) {
    match (base, over) {
        (serde_json::Value::Object(b), serde_json::Value::Object(o)) => {
            for (k, v) in o {
                match b.get_mut(k) {
                    Some(slot) => json_overlay(slot, v),
                    None => {
                        b.insert(k.clone(), v.clone());
                    }
                }
            }
        }
        (slot, v) => *slot = v.clone(),
    }
}

/// |a − b| × 4 per channel, clamped to 1, opaque: the error panel of comparison pictures.
pub fn error_image(a: &[[f32; 4]], b: &[[f32; 4]]) -> Vec<[f32; 4]> {
    a.iter()
        .zip(b)
        .map(|(p, q)| {
            let e = [0, 1, 2].map(|c| ((p[c] - q[c]).abs() * 4.0).min(1.0));
            [e[0], e[1], e[2], 1.0]
        })
        .collect()
}

/// Images of `width`×`height` placed left to right in one picture (`panels.len()`·width wide).
pub fn side_by_side(panels: &[&[[f32; 4]]], width: usize, height: usize) -> Vec<[f32; 4]> {
    let n = panels.len();
    let mut out = vec![[0.0f32; 4]; n * width * height];
    for y in 0..height {
        for (i, p) in panels.iter().enumerate() {
            out[y * n * width + i * width..y * n * width + (i + 1) * width]
                .copy_from_slice(&p[y * width..(y + 1) * width]);
        }
    }
    out
}

/// `secs` as "1 h 02 min", "3 min 05 s" or "12 s".
pub fn duration(secs: f64) -> String {
    let s = secs.max(0.0).round() as u64;
    match s {
        0..60 => format!("{s} s"),
        60..3600 => format!("{} min {:02} s", s / 60, s % 60),
        _ => format!("{} h {:02} min", s / 3600, (s % 3600) / 60),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn one_line_drops_snippets_and_joins_lines() {
        let toml = "TOML parse error at line 1, column 3\n  |\n1 | [[[\n  |   ^\nunquoted keys cannot be empty";
        assert_eq!(one_line(toml), "TOML parse error at line 1, column 3; unquoted keys cannot be empty");
        assert_eq!(
            one_line("invalid type: string \"a\"\nin `iterations`\n"),
            "invalid type: string \"a\"; in `iterations`"
        );
        assert_eq!(one_line("plain"), "plain");
    }

    #[test]
    fn psnr_over_a_region_counts_only_its_pixels() {
        let a = [[0.5f32, 0.5, 0.5, 1.0]; 4];
        let mut b = a;
        b[0] = [0.6, 0.6, 0.6, 1.0];
        // Pixel 0 alone: MSE 0.01, 20 dB; the other pixels are exact; all four: MSE 0.0025.
        assert!((psnr_where(&a, &b, |i| i == 0).unwrap() - 20.0).abs() < 1e-4);
        assert_eq!(psnr_where(&a, &b, |i| i != 0), Some(f64::INFINITY));
        assert_eq!(psnr_where(&a, &b, |_| false), None);
        assert!((psnr(&a, &b) - 10.0 * 400f64.log10()).abs() < 1e-4);
    }
}

/// Seconds between progress lines when the output is not a terminal.
pub const LINE_SECONDS: f64 = 30.0;

/// How a long stage shows its progress on stderr.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ProgressMode {
    /// A bar on a terminal; elsewhere (a log file, a pipe) a plain line every 10 % of the work
    /// or every [`LINE_SECONDS`], whichever comes first.
    Auto,
    /// A line every 10 % only (`--quiet`).
    Tenths,
}

/// Progress of a long stage over `total` steps: an indicatif bar on a terminal, else plain
/// lines `LABELUNIT 30/120: MESSAGE, 2.41 RATE_UNIT, ETA 1 min 05 s`.
pub struct Progress {
    label: String,
    unit: &'static str,
    rate_unit: &'static str,
    total: u64,
    first: u64,
    bar: Option<indicatif::ProgressBar>,
    timed: bool,
    start: std::time::Instant,
    last_line: std::time::Instant,
}

impl Progress {
    /// `label` is printed first (e.g. the pipeline's stage), `unit` names a step ("iteration",
    /// "view") and `rate_unit` its rate ("it/s"); work resumed at step `first` counts its rate
    /// from there.
    pub fn new(
        label: &str,
        unit: &'static str,
        rate_unit: &'static str,
        total: u64,
        first: u64,
        mode: ProgressMode,
    ) -> Progress {
        use std::io::IsTerminal;
        let bar = (mode == ProgressMode::Auto && std::io::stderr().is_terminal()).then(|| {
            let b = indicatif::ProgressBar::new(total);
            b.set_style(
                indicatif::ProgressStyle::with_template(&format!(
                    "{{prefix}}{{bar:30}} {{pos}}/{{len}} {unit}s {{msg}} {{per_sec}} ETA {{eta}}"
                ))
                .expect("a valid progress template"),
            );
            b.set_prefix(label.to_string());
            b.set_position(first);
            b
        });
        let now = std::time::Instant::now();
        Progress {
            label: label.to_string(),
            unit,
            rate_unit,
            total,
            first,
            bar,
            timed: mode == ProgressMode::Auto,
            start: now,
            last_line: now,
        }
    }

    /// `done` steps of `total` are done; `msg` says how it goes (loss, PSNR, …).
    pub fn set(&mut self, done: u64, msg: &str) {
        if let Some(b) = &self.bar {
            b.set_position(done);
            b.set_message(msg.to_string());
            return;
        }
        let tenth = done.is_multiple_of((self.total / 10).max(1));
        let timed = self.timed && self.last_line.elapsed().as_secs_f64() >= LINE_SECONDS;
        if tenth || timed || done == self.total {
            self.last_line = std::time::Instant::now();
            let rate = done.saturating_sub(self.first) as f64 / self.start.elapsed().as_secs_f64().max(1e-9);
            let msg = if msg.is_empty() { String::new() } else { format!(": {msg}") };
            // No estimate before the first step is done (no rate to go by).
            let eta = if done > self.first {
                format!(", ETA {}", duration(self.total.saturating_sub(done) as f64 / rate))
            } else {
                String::new()
            };
            eprintln!("{}{} {done}/{}{msg}, {rate:.2} {}{eta}", self.label, self.unit, self.total, self.rate_unit);
        }
    }

    /// Clears the bar (plain lines stay).
    pub fn finish(self) {
        if let Some(b) = self.bar {
            b.finish_and_clear();
        }
    }
}

/// A message on one line, as the binary prints errors: the lines of a multi-line message (a
/// TOML parse error, say) joined with "; ", source snippets (`1 | text`, `|`, `^^^`) dropped.
pub fn one_line(message: &str) -> String {
    let snippet = |l: &str| {
        let t = l.trim_start_matches(|c: char| c.is_ascii_digit() || c.is_whitespace());
        t.starts_with('|') || (!l.trim().is_empty() && l.trim().chars().all(|c| c == '^' || c == '-' || c == ' '))
    };
    let lines: Vec<&str> = message.lines().filter(|l| !snippet(l)).map(str::trim).filter(|l| !l.is_empty()).collect();
    lines.join("; ")
}
