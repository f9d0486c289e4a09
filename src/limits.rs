//! What a file may make us read (docs/robustness.md, "What a file may make us read").
//!
//! **Confined reads**: a file that names another file (a glTF buffer or image, a SOG
//! `meta.json`'s images, a dataset JSON's `file_path`) may name only a relative path inside its
//! own folder: no `..`, no absolute path, no symbolic link that leads out, and only a regular
//! file (not `/dev/zero`, a pipe or a folder), read with a size limit. Anything else is refused
//! with the file, the field and the path named. `--allow-outside-paths` opens paths outside the
//! folder on purpose (still regular files, still size-limited).
//!
//! **A memory budget per read**: before a reader allocates for what a file declares (buffers ×
//! sizes, a node graph's expanded splats, image dimensions), it checks the bytes against a
//! budget — by default half of the machine's memory, `--max-memory` to change it — and refuses
//! with the figure.
//!
//! The limits are the process's: the binary sets them from its flags once ([`set`]); a library
//! user gets the defaults.
use std::io::Read;
use std::path::{Component, Path, PathBuf};
use std::sync::RwLock;

use anyhow::{bail, Context, Result};

/// The read limits of this process.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Limits {
    /// Files may name paths outside their own folder (`--allow-outside-paths`).
    pub allow_outside: bool,
    /// Bytes one read may hold (`--max-memory`).
    pub max_memory: u64,
}

impl Default for Limits {
    fn default() -> Self {
        Limits { allow_outside: false, max_memory: default_budget() }
    }
}

static LIMITS: RwLock<Option<Limits>> = RwLock::new(None);

/// Sets this process's limits (the binary, from its flags).
pub fn set(limits: Limits) {
    *LIMITS.write().unwrap_or_else(|e| e.into_inner()) = Some(limits);
}

/// This process's limits.
pub fn get() -> Limits {
    LIMITS.read().unwrap_or_else(|e| e.into_inner()).unwrap_or_default()
}

/// Half of the machine's physical memory (4 GiB where it cannot be read).
pub fn default_budget() -> u64 {
    // SAFETY: sysconf has no preconditions; it returns -1 for an unknown name.
    let (pages, size) = unsafe { (libc::sysconf(libc::_SC_PHYS_PAGES), libc::sysconf(libc::_SC_PAGESIZE)) };
    if pages > 0 && size > 0 {
        (pages as u64).saturating_mul(size as u64) / 2
    } else {
        4 << 30
    }
}

/// "1.50 GB" for a byte count.
pub fn size(bytes: u64) -> String {
    if bytes >= 1 << 30 {
        format!("{:.2} GB", bytes as f64 / 1e9)
    } else {
        format!("{:.1} MB", bytes as f64 / 1e6)
    }
}

/// Refuses `bytes` past the memory budget: `{what}: {element} would hold …`.
pub fn check_bytes(what: &str, element: &str, bytes: u64) -> Result<()> {
    let budget = get().max_memory;
    if bytes > budget {
        bail!(
            "{what}: {element} would hold {}, more than the memory budget of {} (--max-memory)",
            size(bytes),
            size(budget)
        );
    }
    Ok(())
}

/// Parses `--max-memory`: bytes, or a number with KB, MB, GB (10³) or KiB, MiB, GiB (2¹⁰).
pub fn parse_bytes(s: &str) -> Result<u64, String> {
    let t = s.trim();
    let split = t.find(|c: char| !(c.is_ascii_digit() || c == '.')).unwrap_or(t.len());
    let (num, unit) = (&t[..split], t[split..].trim());
    let v: f64 = num.parse().map_err(|_| format!("{s:?} is not a size (e.g. 8GB, 512MiB, 1000000)"))?;
    let m = match unit.to_ascii_lowercase().as_str() {
        "" | "b" => 1.0,
        "kb" => 1e3,
        "mb" => 1e6,
        "gb" => 1e9,
        "tb" => 1e12,
        "kib" => 1024.0,
        "mib" => 1024.0 * 1024.0,
        "gib" => 1024.0 * 1024.0 * 1024.0,
        "tib" => 1024.0f64.powi(4),
        _ => return Err(format!("{s:?}: unknown unit {unit:?} (B, KB, MB, GB, TB, KiB, MiB, GiB, TiB)")),
    };
    let bytes = v * m;
    if !(1.0..1.8e19).contains(&bytes) {
        return Err(format!("{s:?} is not a size of at least one byte"));
    }
    Ok(bytes as u64)
}

/// The folder a file's relative paths are relative to.
fn folder_of(file: &Path) -> &Path {
    match file.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    }
}

/// Refuses, by its words alone, a path `name` that `what` names in `field` outside its folder
/// `base` (absolute, or with `..`), unless `--allow-outside-paths`.
pub fn relative(what: &str, field: &str, name: &str, base: &Path) -> Result<()> {
    if name.is_empty() {
        bail!("{what}: {field} names an empty path");
    }
    if name.contains('\0') {
        bail!("{what}: {field} {name:?} holds a NUL byte");
    }
    let rel = Path::new(name);
    let outside =
        rel.is_absolute() || rel.components().any(|c| matches!(c, Component::ParentDir | Component::Prefix(_)));
    if outside && !get().allow_outside {
        bail!(
            "{what}: {field} {name:?} is outside the file's folder (an absolute path or '..'); only files in {} are read (--allow-outside-paths opens others)",
            base.display()
        );
    }
    Ok(())
}

/// Refuses `path` (which `what` names in `field`) unless it is a regular file whose real
/// location (symbolic links followed) is inside `base`, or `--allow-outside-paths` is given.
/// Returns the real path.
pub fn inside(what: &str, field: &str, path: &Path, base: &Path) -> Result<PathBuf> {
    let meta = std::fs::metadata(path).with_context(|| format!("{what}: {field}: cannot read {}", path.display()))?;
    if !meta.is_file() {
        bail!("{what}: {field}: {} is not a regular file", path.display());
    }
    let real =
        std::fs::canonicalize(path).with_context(|| format!("{what}: {field}: cannot resolve {}", path.display()))?;
    if !get().allow_outside {
        let real_base =
            std::fs::canonicalize(base).with_context(|| format!("{what}: cannot resolve {}", base.display()))?;
        if !real.starts_with(&real_base) {
            bail!(
                "{what}: {field}: {} leads outside the file's folder (its real path, links followed, is {}); only files in {} are read (--allow-outside-paths opens others)",
                path.display(),
                real.display(),
                base.display()
            );
        }
    }
    Ok(real)
}

/// The file `name` that the file `referrer` names in `field`, where a confined read allows it
/// (module docs): a relative path inside `referrer`'s folder ([`relative`]), reached without a
/// symbolic link out, that is a regular file ([`inside`]). Returns its real path.
pub fn confined(referrer: &Path, field: &str, name: &str) -> Result<PathBuf> {
    let what = referrer.display().to_string();
    let base = folder_of(referrer);
    relative(&what, field, name, base)?;
    inside(&what, &format!("{field} {name:?}"), &base.join(name), base)
}

/// Reads the regular file at `path` (already [`confined`]): its first `limit` bytes when
/// `whole` is false (what a glTF buffer declares), else the whole file, refused when it holds
/// more than `limit` bytes. The bytes it will hold (the file's size, at most `limit`) are checked
/// against the budget before reading; `what` names the file that asked and `field` its element.
pub fn read_limited(path: &Path, what: &str, field: &str, limit: u64, whole: bool) -> Result<Vec<u8>> {
    let cannot = || format!("{what}: {field}: cannot read {}", path.display());
    let f = std::fs::File::open(path).with_context(cannot)?;
    let len = f.metadata().with_context(cannot)?.len();
    if whole && len > limit {
        bail!(
            "{what}: {field}: {} holds {}, more than {} (the limit of this read)",
            path.display(),
            size(len),
            size(limit)
        );
    }
    let hold = len.min(limit);
    check_bytes(what, field, hold)?;
    let mut out = Vec::new();
    f.take(if whole { hold.saturating_add(1) } else { hold }).read_to_end(&mut out).with_context(cannot)?;
    if out.len() as u64 > hold {
        bail!("{what}: {field}: {} grew while it was read (past the {} it held)", path.display(), size(len));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes_parse_with_their_units() {
        assert_eq!(parse_bytes("1000"), Ok(1000));
        assert_eq!(parse_bytes("8GB"), Ok(8_000_000_000));
        assert_eq!(parse_bytes("512 MiB"), Ok(512 << 20));
        assert_eq!(parse_bytes("1.5kb"), Ok(1500));
        assert!(parse_bytes("-3GB").is_err());
        assert!(parse_bytes("0").is_err());
        assert!(parse_bytes("12 parsecs").is_err());
        assert!(parse_bytes("1e400").is_err());
    }

    #[test]
    fn the_default_budget_is_half_the_memory() {
        let b = default_budget();
        assert!(b >= 256 << 20, "{b}");
    }
}
