//! A glTF document's buffers, read as `crate::limits` allows: the GLB's BIN chunk, base64
//! `data:` URIs and files beside a `.gltf` (confined to its folder, percent-decoded, each read
//! once and only as far as its buffers declare), all within the memory budget.
use std::collections::HashMap;
use std::path::Path;
use std::rc::Rc;

use anyhow::{anyhow, bail, Result};

/// The document's buffers (`byteLength` bytes each; a file named by several buffers read once),
/// checked before anything is read: every buffer's source is the GLB's BIN chunk (buffer 0
/// only), a base64 `data:` URI or a relative path inside the file's folder
/// (`crate::limits::confined`, percent-decoded), and their bytes fit the memory budget.
pub(super) fn load_buffers(
    doc: &gltf::Document,
    what: &str,
    file: Option<&Path>,
    blob: Option<Vec<u8>>,
) -> Result<Vec<Rc<Vec<u8>>>> {
    use gltf::buffer::Source;
    // Unique bytes: the BIN chunk, each data: URI, each file once (at its longest use).
    let mut files: HashMap<std::path::PathBuf, u64> = HashMap::new();
    let mut total = 0u64;
    let mut sources = Vec::new();
    for b in doc.buffers() {
        let (i, len) = (b.index(), b.length() as u64);
        let element = format!("buffer {i}");
        sources.push(match b.source() {
            Source::Bin if i == 0 => {
                let have = blob.as_ref().map_or(0, |v| v.len() as u64);
                if have < len {
                    bail!("{what}: {element} needs {len} bytes of the GLB's BIN chunk, which holds {have}");
                }
                total += len;
                None
            }
            Source::Bin => bail!("{what}: {element} has no uri; only buffer 0 may be the GLB's BIN chunk"),
            Source::Uri(uri) if uri.starts_with("data:") => {
                let encoded = uri.split_once(";base64,").map(|(_, d)| d).ok_or_else(|| {
                    anyhow!("{what}: {element}'s uri is a data: URI that is not base64 (data:…;base64,…)")
                })?;
                total += len.max(encoded.len() as u64 / 4 * 3);
                crate::limits::check_bytes(what, "its buffers", total)?;
                let bytes = base64::decode(encoded).map_err(|e| anyhow!("{what}: {element}'s data: URI: {e}"))?;
                if (bytes.len() as u64) < len {
                    bail!("{what}: {element} declares {len} bytes, its data: URI holds {}", bytes.len());
                }
                Some(Rc::new(bytes))
            }
            Source::Uri(uri) => {
                if uri.split('/').next().is_some_and(|s| s.contains(':')) {
                    bail!(
                        "{what}: {element}'s uri {uri:?} is not a relative path (only files beside the glTF are read)"
                    );
                }
                let name = percent_encoding::percent_decode_str(uri)
                    .decode_utf8()
                    .map_err(|_| anyhow!("{what}: {element}'s uri {uri:?} does not decode to a UTF-8 path"))?;
                let Some(file) = file else {
                    bail!("{what}: {element} names the file {uri:?}, and this glTF was given without its folder");
                };
                let path = crate::limits::confined(file, &format!("{element}'s uri"), &name)?;
                let e = files.entry(path).or_default();
                *e = (*e).max(len);
                None
            }
        });
    }
    total += files.values().sum::<u64>();
    crate::limits::check_bytes(what, "its buffers", total)?;
    let mut read: HashMap<std::path::PathBuf, Rc<Vec<u8>>> = HashMap::new();
    let mut blob = blob.map(Rc::new);
    let mut out = Vec::new();
    for (b, source) in doc.buffers().zip(sources) {
        let len = b.length();
        let data = match (source, b.source()) {
            (Some(d), _) => d,
            (None, gltf::buffer::Source::Bin) => blob.take().unwrap_or_default(),
            (None, gltf::buffer::Source::Uri(uri)) => {
                let name = percent_encoding::percent_decode_str(uri).decode_utf8_lossy().into_owned();
                let element = format!("buffer {}'s uri", b.index());
                let path = crate::limits::confined(file.unwrap_or(Path::new(".")), &element, &name)?;
                match read.get(&path) {
                    Some(d) => d.clone(),
                    None => {
                        let limit = files.get(&path).copied().unwrap_or(len as u64);
                        let d = Rc::new(crate::limits::read_limited(&path, what, &element, limit, false)?);
                        read.insert(path, d.clone());
                        d
                    }
                }
            }
        };
        if data.len() < len {
            bail!("{what}: buffer {} declares {len} bytes, its file holds {}", b.index(), data.len());
        }
        out.push(data);
    }
    Ok(out)
}
