//! Product-quantised instance offsets (`.instgs` offset dtype `pq8`, and the GPU's compact
//! offsets): each (template Gaussian, instance) pair keeps two 8-bit codes, one into a
//! 256-entry codebook of Δp (3 floats) and one into a 256-entry codebook of (Δ SH DC, Δ opacity
//! logit) (4 floats): 2 bytes per pair instead of 28, the codebooks 7 KiB per group. Codebooks
//! are k-means centroids (Lloyd iterations on a sample, as the compact-3DGS vector quantisers
//! do); offsets that already take at most 256 distinct values per part (a decoded `pq8` file)
//! are coded exactly.
use std::collections::HashMap;

use rand::{Rng, SeedableRng};

use crate::model::instanced::Offsets;

/// Codebook entries per part.
pub const CODES: usize = 256;
/// Vectors the k-means sees at most (the rest are only assigned).
const SAMPLE: usize = 65_536;
const ITERATIONS: usize = 12;

#[derive(Clone, Debug, PartialEq)]
pub struct OffsetCodes {
    /// Per pair (offset order): [Δp code, (Δ SH DC, Δ opacity) code].
    pub codes: Vec<[u8; 2]>,
    /// Δp codebook, CODES entries.
    pub dp: Vec<[f32; 3]>,
    /// (Δ SH DC rgb, Δ opacity logit) codebook, CODES entries.
    pub dc: Vec<[f32; 4]>,
}

fn parts(o: &Offsets) -> (Vec<[f32; 3]>, Vec<[f32; 4]>) {
    let dc = o.d_sh0.iter().zip(&o.d_opacities).map(|(c, &a)| [c[0], c[1], c[2], a]).collect();
    (o.d_means.clone(), dc)
}

/// The distinct vectors of `v` and each one's index, if there are at most CODES of them.
fn distinct<const D: usize>(v: &[[f32; D]]) -> Option<(Vec<[f32; D]>, Vec<u8>)> {
    let mut map: HashMap<[u32; D], u8> = HashMap::new();
    let mut book = Vec::new();
    let mut idx = Vec::with_capacity(v.len());
    for x in v {
        let key = x.map(f32::to_bits);
        let i = match map.get(&key) {
            Some(&i) => i,
            None => {
                if book.len() == CODES {
                    return None;
                }
                book.push(*x);
                map.insert(key, (book.len() - 1) as u8);
                (book.len() - 1) as u8
            }
        };
        idx.push(i);
    }
    book.resize(CODES, [0.0; D]);
    Some((book, idx))
}

fn dist2<const D: usize>(a: &[f32; D], b: &[f32; D]) -> f32 {
    a.iter().zip(b).map(|(x, y)| (x - y) * (x - y)).sum()
}

fn nearest<const D: usize>(book: &[[f32; D]], x: &[f32; D]) -> u8 {
    let mut best = (f32::INFINITY, 0);
    for (i, c) in book.iter().enumerate() {
        let d = dist2(c, x);
        if d < best.0 {
            best = (d, i);
        }
    }
    best.1 as u8
}

/// k-means codebook of `v` (Lloyd iterations on a seeded sample; empty clusters take a random
/// sample vector).
fn kmeans<const D: usize>(v: &[[f32; D]], seed: u64) -> Vec<[f32; D]> {
    let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
    let sample: Vec<[f32; D]> =
        if v.len() <= SAMPLE { v.to_vec() } else { (0..SAMPLE).map(|_| v[rng.random_range(0..v.len())]).collect() };
    let mut book: Vec<[f32; D]> = (0..CODES).map(|_| sample[rng.random_range(0..sample.len())]).collect();
    for _ in 0..ITERATIONS {
        let mut sum = [[0.0f64; D]; CODES];
        let mut count = [0usize; CODES];
        for x in &sample {
            let c = nearest(&book, x) as usize;
            count[c] += 1;
            for d in 0..D {
                sum[c][d] += x[d] as f64;
            }
        }
        for c in 0..CODES {
            book[c] = if count[c] == 0 {
                sample[rng.random_range(0..sample.len())]
            } else {
                std::array::from_fn(|d| (sum[c][d] / count[c] as f64) as f32)
            };
        }
    }
    book
}

impl OffsetCodes {
    /// Exact codes when every part takes at most CODES distinct values, else None.
    pub fn exact(o: &Offsets) -> Option<OffsetCodes> {
        let (p, c) = parts(o);
        let (dp, ip) = distinct(&p)?;
        let (dc, ic) = distinct(&c)?;
        Some(OffsetCodes { codes: ip.into_iter().zip(ic).map(|(a, b)| [a, b]).collect(), dp, dc })
    }

    /// Codes for `o`: exact where possible, else k-means codebooks (lossy).
    pub fn encode(o: &Offsets, seed: u64) -> OffsetCodes {
        if let Some(c) = OffsetCodes::exact(o) {
            return c;
        }
        let (p, c) = parts(o);
        let dp = kmeans(&p, seed);
        let dc = kmeans(&c, seed ^ 0x9e37_79b9);
        let mut codes = OffsetCodes { codes: Vec::new(), dp, dc };
        codes.codes = codes.assign(o);
        codes
    }

    /// The nearest codes of `o` in these codebooks.
    pub fn assign(&self, o: &Offsets) -> Vec<[u8; 2]> {
        let (p, c) = parts(o);
        p.iter().zip(&c).map(|(a, b)| [nearest(&self.dp, a), nearest(&self.dc, b)]).collect()
    }

    pub fn decode(&self) -> Offsets {
        let mut o = Offsets::zeros(self.codes.len());
        for (i, [a, b]) in self.codes.iter().enumerate() {
            let c = self.dc[*b as usize];
            o.d_means[i] = self.dp[*a as usize];
            o.d_sh0[i] = [c[0], c[1], c[2]];
            o.d_opacities[i] = c[3];
        }
        o
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn random(n: usize, seed: u64, sigma: f32) -> Offsets {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
        let mut o = Offsets::zeros(n);
        for i in 0..n {
            o.d_means[i] = std::array::from_fn(|_| sigma * rng.random_range(-1.0..1.0));
            o.d_sh0[i] = std::array::from_fn(|_| sigma * rng.random_range(-1.0..1.0));
            o.d_opacities[i] = sigma * rng.random_range(-1.0..1.0);
        }
        o
    }

    #[test]
    fn decoded_codes_are_coded_exactly_again() {
        let o = random(20_000, 1, 0.05);
        let c = OffsetCodes::encode(&o, 3);
        let d = c.decode();
        // Lossy once: the error is a fraction of the spread.
        let err: f32 = o.d_means.iter().zip(&d.d_means).map(|(a, b)| dist2(a, b)).sum::<f32>() / o.len() as f32;
        let var: f32 = o.d_means.iter().map(|a| dist2(a, &[0.0; 3])).sum::<f32>() / o.len() as f32;
        assert!(err < 0.1 * var, "quantisation error {err} vs variance {var}");
        // Then exact: decoding the re-encoded codes gives the same offsets bit for bit.
        let again = OffsetCodes::exact(&d).expect("at most 256 distinct values per part");
        assert_eq!(again.decode(), d);
        assert!(OffsetCodes::exact(&o).is_none());
    }

    #[test]
    fn zero_offsets_are_one_code() {
        let c = OffsetCodes::exact(&Offsets::zeros(10)).unwrap();
        assert!(c.codes.iter().all(|&x| x == [0, 0]));
        assert_eq!(c.decode(), Offsets::zeros(10));
    }
}
