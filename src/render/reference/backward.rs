//! CPU twins (f64) of the training kernels: the projection of one Gaussian and its vector-Jacobian
//! product (`preprocess_backward`), compositing and its backward (`blend_backward`), the
//! L1 + D-SSIM loss with its image gradient (`loss_*`), and Adam (`adam`). The tests check the
//! kernels against these and these against central finite differences.
use crate::math::{rotation, rotation_vjp, sh_basis_grad};
use glam::{DMat2, DMat3, DMat4, DVec2, DVec3, DVec4};

use crate::shared::{FrameParams, TILE_SIZE};

/// One Gaussian's parameters (as stored: log scales, raw wxyz quaternion, opacity logit, SH
/// coefficients `[k][channel]` flattened).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Gaussian {
    pub mean: [f64; 3],
    pub scale: [f64; 3],
    pub quat: [f64; 4],
    pub opacity: f64,
    pub sh: Vec<f64>,
}

impl Gaussian {
    /// Gaussian `i` of a scene.
    pub fn of_scene(s: &crate::model::scene::Scene, i: usize) -> Gaussian {
        let k = s.sh_coeffs() * 3;
        Gaussian {
            mean: s.means[i].map(f64::from),
            scale: s.scales[i].map(f64::from),
            quat: s.quats[i].map(f64::from),
            opacity: s.opacities[i] as f64,
            sh: s.sh[i * k..(i + 1) * k].iter().map(|&v| v as f64).collect(),
        }
    }

    /// All parameters in one vector (mean, scale, quat, opacity, sh): for finite differences.
    pub fn flat(&self) -> Vec<f64> {
        let mut v: Vec<f64> = self.mean.iter().chain(&self.scale).chain(&self.quat).copied().collect();
        v.push(self.opacity);
        v.extend(&self.sh);
        v
    }

    pub fn from_flat(v: &[f64]) -> Gaussian {
        Gaussian {
            mean: [v[0], v[1], v[2]],
            scale: [v[3], v[4], v[5]],
            quat: [v[6], v[7], v[8], v[9]],
            opacity: v[10],
            sh: v[11..].to_vec(),
        }
    }
}

/// A projected splat: what `preprocess` writes and `blend` reads.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Splat {
    pub xy: [f64; 2],
    /// (a, b, c) of power = -(a dx² + c dy²)/2 - b dx dy.
    pub conic: [f64; 3],
    pub opacity: f64,
    pub colour: [f64; 3],
}

impl Splat {
    pub fn flat(&self) -> [f64; 9] {
        let (x, c, o, r) = (self.xy, self.conic, self.opacity, self.colour);
        [x[0], x[1], c[0], c[1], c[2], o, r[0], r[1], r[2]]
    }

    pub fn from_flat(v: &[f64]) -> Splat {
        Splat { xy: [v[0], v[1]], conic: [v[2], v[3], v[4]], opacity: v[5], colour: [v[6], v[7], v[8]] }
    }

    /// The GPU/CPU forward's f32 values of Gaussian `i`.
    pub fn of_projected(p: &crate::render::reference::forward::Projected, i: usize) -> Splat {
        let (x, c, r) = (p.xys[i], p.conics[i], p.colours[i]);
        Splat {
            xy: x.map(f64::from),
            conic: [c[0] as f64, c[1] as f64, c[2] as f64],
            opacity: c[3] as f64,
            colour: [r[0] as f64, r[1] as f64, r[2] as f64],
        }
    }
}

/// The camera quantities of the projection, in f64.
struct Proj {
    view: DMat4,
    w: DMat3,
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
    lim: [f64; 4],
    campos: DVec3,
}

fn proj(fp: &FrameParams) -> Proj {
    let view = DMat4::from_cols_array_2d(&fp.viewmat.map(|c| c.map(f64::from)));
    let [fx, fy, cx, cy] = fp.intrinsics.map(f64::from);
    let (width, height) = (fp.width as f64, fp.height as f64);
    let tx = 0.5 * width / fx;
    let ty = 0.5 * height / fy;
    Proj {
        view,
        w: DMat3::from_mat4(view),
        fx,
        fy,
        cx,
        cy,
        lim: [(width - cx) / fx + 0.3 * tx, cx / fx + 0.3 * tx, (height - cy) / fy + 0.3 * ty, cy / fy + 0.3 * ty],
        campos: DVec3::new(fp.campos[0] as f64, fp.campos[1] as f64, fp.campos[2] as f64),
    }
}

/// The intermediate values of one projection, shared by forward and VJP.
struct Fwd {
    t: DVec3,
    q: DVec4,
    q_len: f64,
    r: DMat3,
    s: DVec3,
    m: DMat3,
    v: DMat3,
    j0: DVec3,
    j1: DVec3,
    cu: [f64; 2],
    free: [bool; 2],
    cov: [f64; 3],
    dir: DVec3,
    dir_len: f64,
    basis: [f64; 16],
    dbasis: [DVec3; 16],
    rgb_raw: DVec3,
}

fn forward(pr: &Proj, g: &Gaussian, sh_degree: u32) -> Fwd {
    let p = DVec3::from(g.mean);
    let t = (pr.view * p.extend(1.0)).truncate();
    let q_raw = DVec4::from(g.quat);
    let q_len = q_raw.length();
    let q = q_raw / q_len;
    let r = rotation(q);
    let s = DVec3::from(g.scale).exp();
    let m = r * DMat3::from_diagonal(s);
    let v = pr.w * (m * m.transpose()) * pr.w.transpose();
    let rz = 1.0 / t.z;
    let (ux, uy) = (t.x * rz, t.y * rz);
    let cux = ux.max(-pr.lim[1]).min(pr.lim[0]);
    let cuy = uy.max(-pr.lim[3]).min(pr.lim[2]);
    let j0 = DVec3::new(pr.fx * rz, 0.0, -pr.fx * cux * rz);
    let j1 = DVec3::new(0.0, pr.fy * rz, -pr.fy * cuy * rz);
    let cov = [j0.dot(v * j0) + 0.3, j0.dot(v * j1), j1.dot(v * j1) + 0.3];
    let dv = p - pr.campos;
    let dir_len = dv.length();
    let dir = dv / dir_len;
    let (basis, dbasis) = sh_basis_grad(dir, sh_degree);
    let nb = ((sh_degree + 1) * (sh_degree + 1)) as usize;
    let mut rgb = DVec3::ZERO;
    for (k, b) in basis.iter().enumerate().take(nb) {
        rgb += *b * DVec3::new(g.sh[3 * k], g.sh[3 * k + 1], g.sh[3 * k + 2]);
    }
    Fwd {
        t,
        q,
        q_len,
        r,
        s,
        m,
        v,
        j0,
        j1,
        cu: [cux, cuy],
        free: [ux == cux, uy == cuy],
        cov,
        dir,
        dir_len,
        basis,
        dbasis,
        rgb_raw: rgb + 0.5,
    }
}

/// The projected splat of `g` (no culling: the caller decides visibility). `fp.sh_degree` is the
/// degree evaluated.
pub fn project(fp: &FrameParams, g: &Gaussian) -> Splat {
    let pr = proj(fp);
    let f = forward(&pr, g, fp.sh_degree);
    let [a, b, c] = f.cov;
    let det = a * c - b * b;
    let rz = 1.0 / f.t.z;
    Splat {
        xy: [pr.fx * f.t.x * rz + pr.cx, pr.fy * f.t.y * rz + pr.cy],
        conic: [c / det, -b / det, a / det],
        opacity: 1.0 / (1.0 + (-g.opacity).exp()),
        colour: f.rgb_raw.max(DVec3::ZERO).to_array(),
    }
}

/// The vector-Jacobian product of [`project`]: gradients of the parameters given `v`, the
/// gradient with respect to the splat, plus the frame-cost regulariser's
/// `fp.tile_cost_weight × tiles_touched` on each log-scale (the splat's tile count, held
/// constant). Mirrors `preprocess_backward.comp`.
pub fn project_vjp(fp: &FrameParams, g: &Gaussian, v: &Splat, tiles_touched: u32) -> Gaussian {
    vjp(fp, g, v, tiles_touched).0
}

/// The camera-gradient terms of [`project`] given `v` (`preprocess_backward`'s with
/// CAMERA_GRADS): dL/dW (column-major) and dL/dt of viewmat = [W | t] with the camera centre
/// held, then dL/dcampos through the SH view direction (`CAMERA_GRAD_TERMS` values).
pub fn project_camera_vjp(fp: &FrameParams, g: &Gaussian, v: &Splat) -> [f64; 15] {
    vjp(fp, g, v, 0).1
}

/// [`project_vjp`] and [`project_camera_vjp`] in one pass.
fn vjp(fp: &FrameParams, g: &Gaussian, v: &Splat, tiles_touched: u32) -> (Gaussian, [f64; 15]) {
    let pr = proj(fp);
    let f = forward(&pr, g, fp.sh_degree);
    let [a, b, c] = f.cov;
    let inv_det = 1.0 / (a * c - b * b);
    let q_mat = DMat2::from_cols_array(&[c, -b, -b, a]) * inv_det;
    let gq = DMat2::from_cols_array(&[v.conic[0], 0.5 * v.conic[1], 0.5 * v.conic[1], v.conic[2]]);
    let gs = -(q_mat * gq * q_mat);
    let (va, vb, vc) = (gs.x_axis.x, gs.x_axis.y + gs.y_axis.x, gs.y_axis.y);
    let (j0, j1) = (f.j0, f.j1);
    let outer = |u: DVec3, w: DVec3| DMat3::from_cols(u * w.x, u * w.y, u * w.z);
    let v_v = outer(j0, j0) * va + (outer(j0, j1) + outer(j1, j0)) * (0.5 * vb) + outer(j1, j1) * vc;
    let (vj0, vj1) = (f.v * j0, f.v * j1);
    let v_j0 = vj0 * (2.0 * va) + vj1 * vb;
    let v_j1 = vj0 * vb + vj1 * (2.0 * vc);
    let t = f.t;
    let rz = 1.0 / t.z;
    let (fx, fy) = (pr.fx, pr.fy);
    let (dux_dtx, dux_dz) = if f.free[0] { (rz, -t.x * rz * rz) } else { (0.0, 0.0) };
    let (duy_dty, duy_dz) = if f.free[1] { (rz, -t.y * rz * rz) } else { (0.0, 0.0) };
    let mut v_t = DVec3::ZERO;
    v_t.x += v_j0.z * (-fx * rz) * dux_dtx;
    v_t.y += v_j1.z * (-fy * rz) * duy_dty;
    v_t.z += v_j0.x * (-fx * rz * rz) + v_j0.z * (fx * f.cu[0] * rz * rz - fx * rz * dux_dz);
    v_t.z += v_j1.y * (-fy * rz * rz) + v_j1.z * (fy * f.cu[1] * rz * rz - fy * rz * duy_dz);
    v_t.x += v.xy[0] * fx * rz;
    v_t.y += v.xy[1] * fy * rz;
    v_t.z -= (v.xy[0] * fx * t.x + v.xy[1] * fy * t.y) * rz * rz;

    let v_sigma = pr.w.transpose() * v_v * pr.w;
    let v_m = v_sigma * f.m * 2.0;
    let v_s = DVec3::new(v_m.x_axis.dot(f.r.x_axis), v_m.y_axis.dot(f.r.y_axis), v_m.z_axis.dot(f.r.z_axis));
    let v_r = v_m * DMat3::from_diagonal(f.s);
    let v_q = rotation_vjp(f.q, v_r);
    let v_q = (v_q - f.q * f.q.dot(v_q)) / f.q_len;

    let nb = ((fp.sh_degree + 1) * (fp.sh_degree + 1)) as usize;
    let mut v_rgb = DVec3::from(v.colour);
    for ch in 0..3 {
        if f.rgb_raw[ch] <= 0.0 {
            v_rgb[ch] = 0.0;
        }
    }
    let mut v_sh = vec![0.0; g.sh.len()];
    let mut v_dir = DVec3::ZERO;
    for k in 0..nb {
        let gk = f.basis[k] * v_rgb;
        v_sh[3 * k..3 * k + 3].copy_from_slice(&gk.to_array());
        let ck = DVec3::new(g.sh[3 * k], g.sh[3 * k + 1], g.sh[3 * k + 2]);
        v_dir += f.dbasis[k] * ck.dot(v_rgb);
    }
    let v_dir_p = (v_dir - f.dir * f.dir.dot(v_dir)) / f.dir_len;
    let v_p = pr.w.transpose() * v_t + v_dir_p;
    let v_w = outer(v_t, DVec3::from(g.mean)) + v_v * pr.w * (f.m * f.m.transpose()) * 2.0;
    let mut camera = [0.0; 15];
    camera[..9].copy_from_slice(&v_w.to_cols_array());
    camera[9..12].copy_from_slice(&v_t.to_array());
    camera[12..].copy_from_slice(&(-v_dir_p).to_array());
    let o = 1.0 / (1.0 + (-g.opacity).exp());
    let grads = Gaussian {
        mean: v_p.to_array(),
        scale: (v_s * f.s + DVec3::splat(fp.tile_cost_weight as f64 * tiles_touched as f64)).to_array(),
        quat: v_q.to_array(),
        opacity: v.opacity * o * (1.0 - o),
        sh: v_sh,
    };
    (grads, camera)
}

/// Forward compositing of every pixel in f64 with the forward's rules (skip power > 0 and
/// alpha < 1/255, stop before T < 1e-4), given the tile ranges and tile-sorted ids. Returns the
/// RGB image (with background) and, per pixel, the final T and the splat count `last`.
pub fn blend(
    fp: &FrameParams,
    ranges: &[[u32; 2]],
    isect_ids: &[u32],
    splats: &[Splat],
) -> (Vec<[f64; 3]>, Vec<f64>, Vec<u32>) {
    let (w, h) = (fp.width as usize, fp.height as usize);
    let bg = DVec3::new(fp.background[0] as f64, fp.background[1] as f64, fp.background[2] as f64);
    let mut img = vec![[0.0; 3]; w * h];
    let mut ts = vec![1.0; w * h];
    let mut lasts = vec![0u32; w * h];
    for py in 0..h {
        for px in 0..w {
            let ids = tile_ids(fp, ranges, isect_ids, px, py);
            let pixf = DVec2::new(px as f64 + 0.5, py as f64 + 0.5);
            let mut t = 1.0;
            let mut c = DVec3::ZERO;
            for (n, &id) in ids.iter().enumerate() {
                let s = &splats[id as usize];
                let Some((alpha, _, _)) = splat_alpha(s, pixf) else { continue };
                let test_t = t * (1.0 - alpha);
                if test_t < 1e-4 {
                    break;
                }
                c += DVec3::from(s.colour) * alpha * t;
                t = test_t;
                lasts[py * w + px] = n as u32 + 1;
            }
            img[py * w + px] = (c + t * bg).to_array();
            ts[py * w + px] = t;
        }
    }
    (img, ts, lasts)
}

fn tile_ids<'a>(fp: &FrameParams, ranges: &[[u32; 2]], isect_ids: &'a [u32], px: usize, py: usize) -> &'a [u32] {
    let tile = (py / TILE_SIZE as usize) * fp.tiles_x as usize + px / TILE_SIZE as usize;
    let [a, b] = ranges[tile];
    &isect_ids[a as usize..b as usize]
}

/// (alpha, G, d) of a splat at a pixel centre, or None where blend skips it.
fn splat_alpha(s: &Splat, pixf: DVec2) -> Option<(f64, f64, DVec2)> {
    let d = DVec2::from(s.xy) - pixf;
    let co = s.conic;
    let power = -0.5 * (co[0] * d.x * d.x + co[2] * d.y * d.y) - co[1] * d.x * d.y;
    if power > 0.0 {
        return None;
    }
    let g = power.exp();
    let alpha = (s.opacity * g).min(0.99);
    (alpha >= 1.0 / 255.0).then_some((alpha, g, d))
}

/// Backward of [`blend`]: dL/d splat for every splat, given dL/d rgb per pixel. Follows the
/// forward's decisions exactly (same skips, same saturation stop) with T from the forward.
pub fn blend_backward(
    fp: &FrameParams,
    ranges: &[[u32; 2]],
    isect_ids: &[u32],
    splats: &[Splat],
    v_image: &[[f64; 3]],
) -> Vec<Splat> {
    let (w, h) = (fp.width as usize, fp.height as usize);
    let bg = DVec3::new(fp.background[0] as f64, fp.background[1] as f64, fp.background[2] as f64);
    let mut grads = vec![Splat::default(); splats.len()];
    for py in 0..h {
        for px in 0..w {
            let ids = tile_ids(fp, ranges, isect_ids, px, py);
            let pixf = DVec2::new(px as f64 + 0.5, py as f64 + 0.5);
            // Forward, recording the blended splats with T before each.
            let mut used = Vec::new();
            let mut t = 1.0;
            for &id in ids {
                let s = &splats[id as usize];
                let Some((alpha, g, d)) = splat_alpha(s, pixf) else { continue };
                let test_t = t * (1.0 - alpha);
                if test_t < 1e-4 {
                    break;
                }
                used.push((id as usize, alpha, g, d, t));
                t = test_t;
            }
            let t_final = t;
            let v_pix = DVec3::from(v_image[py * w + px]);
            let mut behind = DVec3::ZERO;
            for &(id, alpha, g, d, t_i) in used.iter().rev() {
                let s = &splats[id];
                let rgb = DVec3::from(s.colour);
                let gr = &mut grads[id];
                for ch in 0..3 {
                    gr.colour[ch] += alpha * t_i * v_pix[ch];
                }
                let v_alpha = t_i * (rgb - behind).dot(v_pix) - t_final / (1.0 - alpha) * bg.dot(v_pix);
                behind = alpha * rgb + (1.0 - alpha) * behind;
                if s.opacity * g <= 0.99 {
                    let v_g = s.opacity * v_alpha;
                    let co = s.conic;
                    let (gdx, gdy) = (g * d.x, g * d.y);
                    gr.xy[0] += v_g * (-gdx * co[0] - gdy * co[1]);
                    gr.xy[1] += v_g * (-gdy * co[2] - gdx * co[1]);
                    gr.conic[0] += v_g * (-0.5 * gdx * d.x);
                    gr.conic[1] += v_g * (-gdx * d.y);
                    gr.conic[2] += v_g * (-0.5 * gdy * d.y);
                    gr.opacity += g * v_alpha;
                }
            }
        }
    }
    grads
}

/// SSIM window weights (11 taps, σ = 1.5, normalised).
pub fn ssim_window() -> [f64; 11] {
    let mut w = [0.0; 11];
    for (k, wk) in w.iter_mut().enumerate() {
        let x = k as f64 - 5.0;
        *wk = (-x * x / (2.0 * 1.5 * 1.5)).exp();
    }
    let s: f64 = w.iter().sum();
    w.map(|v| v / s)
}

/// Separable zero-padded Gaussian filter of one plane (w × h, row-major).
pub fn gauss_filter(src: &[f64], w: usize, h: usize) -> Vec<f64> {
    filter_axis(&filter_axis(src, w, h, true), w, h, false)
}

/// The 11-tap window along x (`horizontal`) or y, zero outside the plane.
fn filter_axis(src: &[f64], w: usize, h: usize, horizontal: bool) -> Vec<f64> {
    let win = ssim_window();
    let mut out = vec![0.0; w * h];
    for y in 0..h {
        for x in 0..w {
            let (pos, len) = if horizontal { (x, w) } else { (y, h) };
            let mut acc = 0.0;
            for (k, wk) in win.iter().enumerate() {
                let q = pos as i64 + k as i64 - 5;
                if (0..len as i64).contains(&q) {
                    let q = q as usize;
                    acc += wk * if horizontal { src[y * w + q] } else { src[q * w + x] };
                }
            }
            out[y * w + x] = acc;
        }
    }
    out
}

/// The SSIM map of one channel plane pair and the three cotangent maps dS/dμx (total),
/// dS/dE(x²), dS/dE(xy) (for the gradient).
pub fn ssim_plane(x: &[f64], y: &[f64], w: usize, h: usize) -> (Vec<f64>, [Vec<f64>; 3]) {
    const C1: f64 = 0.0001;
    const C2: f64 = 0.0009;
    let f = |v: Vec<f64>| gauss_filter(&v, w, h);
    let mx = f(x.to_vec());
    let my = f(y.to_vec());
    let exx = f(x.iter().map(|a| a * a).collect());
    let eyy = f(y.iter().map(|a| a * a).collect());
    let exy = f(x.iter().zip(y).map(|(a, b)| a * b).collect());
    let n = w * h;
    let mut s = vec![0.0; n];
    let mut cot = [vec![0.0; n], vec![0.0; n], vec![0.0; n]];
    for i in 0..n {
        let (ux, uy) = (mx[i], my[i]);
        let sxx = exx[i] - ux * ux;
        let syy = eyy[i] - uy * uy;
        let sxy = exy[i] - ux * uy;
        let (a1, a2) = (2.0 * ux * uy + C1, 2.0 * sxy + C2);
        let (b1, b2) = (ux * ux + uy * uy + C1, sxx + syy + C2);
        let si = a1 * a2 / (b1 * b2);
        let d_exx = -si / b2;
        let d_exy = 2.0 * a1 / (b1 * b2);
        s[i] = si;
        cot[0][i] = 2.0 * uy * a2 / (b1 * b2) - si * 2.0 * ux / b1 - 2.0 * ux * d_exx - uy * d_exy;
        cot[1][i] = d_exx;
        cot[2][i] = d_exy;
    }
    (s, cot)
}

/// The training loss (1 − λ)·mean|x − y| + λ·(1 − mean SSIM) over pixels and channels of two RGB
/// images (w × h) and its gradient with respect to `x`. Returns (loss, mean L1, mean SSIM, grad).
pub fn loss(x: &[[f64; 3]], y: &[[f64; 3]], w: usize, h: usize, lambda: f64) -> (f64, f64, f64, Vec<[f64; 3]>) {
    let n = w * h;
    let count = (3 * n) as f64;
    let mut grad = vec![[0.0; 3]; n];
    let (mut l1, mut ssim) = (0.0, 0.0);
    for ch in 0..3 {
        let xc: Vec<f64> = x.iter().map(|p| p[ch]).collect();
        let yc: Vec<f64> = y.iter().map(|p| p[ch]).collect();
        let (s, cot) = ssim_plane(&xc, &yc, w, h);
        ssim += s.iter().sum::<f64>();
        let f: Vec<Vec<f64>> = cot.iter().map(|c| gauss_filter(c, w, h)).collect();
        for i in 0..n {
            let d = xc[i] - yc[i];
            l1 += d.abs();
            let g_ssim = f[0][i] + 2.0 * xc[i] * f[1][i] + yc[i] * f[2][i];
            grad[i][ch] = -lambda / count * g_ssim + (1.0 - lambda) / count * d.signum() * (d != 0.0) as u8 as f64;
        }
    }
    let (l1, ssim) = (l1 / count, ssim / count);
    ((1.0 - lambda) * l1 + lambda * (1.0 - ssim), l1, ssim, grad)
}

/// Mean SSIM of two RGB images (the loss's definition: zero padding, every pixel counted).
pub fn ssim(x: &[[f64; 3]], y: &[[f64; 3]], w: usize, h: usize) -> f64 {
    let mut total = 0.0;
    for ch in 0..3 {
        let xc: Vec<f64> = x.iter().map(|p| p[ch]).collect();
        let yc: Vec<f64> = y.iter().map(|p| p[ch]).collect();
        total += ssim_plane(&xc, &yc, w, h).0.iter().sum::<f64>();
    }
    total / (3 * w * h) as f64
}

/// Adam hyper-parameters of one step (torch.optim.Adam semantics, `step` counted from 1).
#[derive(Clone, Copy, Debug)]
pub struct AdamStep {
    pub lr: f64,
    pub beta1: f64,
    pub beta2: f64,
    pub eps: f64,
    pub step: u64,
}

/// One Adam step on a parameter slice (the twin of `adam.comp`, in f64).
pub fn adam(params: &mut [f64], grads: &[f64], m: &mut [f64], v: &mut [f64], a: AdamStep) {
    let bc1 = 1.0 - a.beta1.powi(a.step as i32);
    let bc2 = 1.0 - a.beta2.powi(a.step as i32);
    for i in 0..params.len() {
        let g = grads[i];
        m[i] += (g - m[i]) * (1.0 - a.beta1);
        v[i] = a.beta2 * v[i] + (1.0 - a.beta2) * g * g;
        params[i] -= a.lr / bc1 * m[i] / (v[i].sqrt() / bc2.sqrt() + a.eps);
    }
}
