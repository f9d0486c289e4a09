//! The CPU twin of the forward rasterizer: one function per GPU pass, the same rules in the
//! same order (f32), used by the tests to check every kernel and the whole image.
use crate::math::{quat_to_mat, sh_basis};
use glam::{Mat3, Vec2, Vec3};

use crate::model::scene::Scene;
use crate::shared::{FrameParams, MAX_GROUPS, QUAD_VERTICES, SCAN_BLOCK, TILE_SIZE, WG_SIZE};

/// Per-Gaussian output of the preprocess pass (GPU buffers of the same names). A culled
/// Gaussian has tiles_touched = 0 and radii 0; its other values are unspecified (zero here).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Projected {
    pub xys: Vec<[f32; 2]>,
    /// Conic (a, b, c of the inverse 2D covariance) and opacity.
    pub conics: Vec<[f32; 4]>,
    /// RGB (a unused).
    pub colours: Vec<[f32; 4]>,
    pub depths: Vec<f32>,
    /// Half-extents in pixels along x and y.
    pub radii: Vec<[u32; 2]>,
    pub tiles_touched: Vec<u32>,
}

/// The tiles [lo, hi) holding a pixel centre within `radius` (per axis) of `xy`: conservative,
/// as gsplat (Inria's getRect can miss the last partly covered tile).
pub fn tile_rect(fp: &FrameParams, xy: [f32; 2], radius: [u32; 2]) -> ([i32; 2], [i32; 2]) {
    let t = TILE_SIZE as f32;
    let grid = [fp.tiles_x as f32, fp.tiles_y as f32];
    let mut lo = [0; 2];
    let mut hi = [0; 2];
    for a in 0..2 {
        let r = radius[a] as f32;
        lo[a] = ((xy[a] - r - 0.5) / t).floor().clamp(0.0, grid[a]) as i32;
        hi[a] = (((xy[a] + r - 0.5) / t).floor() + 1.0).clamp(0.0, grid[a]) as i32;
    }
    (lo, hi)
}

/// The tiles (x, y) of a tile rectangle [lo, hi), row by row.
pub fn rect_tiles(lo: [i32; 2], hi: [i32; 2]) -> impl Iterator<Item = [i32; 2]> {
    (lo[1]..hi[1]).flat_map(move |y| (lo[0]..hi[0]).map(move |x| [x, y]))
}

/// `splat_hits_tile` (tiles.glsl): whether splat (xy, co) can reach alpha >= 1/255 at a pixel
/// centre of tile `tile`, by the least q = a dx^2 + 2 b dx dy + c dy^2 over the rectangle of
/// the tile's pixel centres (same f32 operations in the same order, no fused multiply-adds).
pub fn splat_hits_tile(xy: [f32; 2], co: [f32; 4], tile: [i32; 2]) -> bool {
    let t = TILE_SIZE as i32;
    let lo = [(tile[0] * t) as f32 + 0.5 - xy[0], (tile[1] * t) as f32 + 0.5 - xy[1]];
    let hi = [lo[0] + (TILE_SIZE - 1) as f32, lo[1] + (TILE_SIZE - 1) as f32];
    let mut q = 0.0f32;
    if lo[0] > 0.0 || hi[0] < 0.0 || lo[1] > 0.0 || hi[1] < 0.0 {
        q = 3.0e38;
        for e in 0..2 {
            let x = if e == 0 { lo[0] } else { hi[0] };
            let dy = (-co[1] * x / co[2]).clamp(lo[1], hi[1]);
            q = q.min(co[0] * x * x + 2.0 * co[1] * x * dy + co[2] * dy * dy);
            let y = if e == 0 { lo[1] } else { hi[1] };
            let dx = (-co[1] * y / co[0]).clamp(lo[0], hi[0]);
            q = q.min(co[0] * dx * dx + 2.0 * co[1] * dx * y + co[2] * y * y);
        }
    }
    let lim = (2.0 * (255.0 * co[3]).ln()).max(0.0) * 1.001 + 0.001;
    q <= lim
}

/// Pass `preprocess`: cull, project, conic, radii, tiles touched, SH colour, depth. The radii
/// are per axis: Inria's 3σ square clipped to the bounding box of the ellipse where alpha can
/// still reach 1/255 (same image, fewer empty intersections).
pub fn preprocess(scene: &Scene, fp: &FrameParams) -> Projected {
    let n = scene.len();
    let mut p = Projected {
        xys: vec![[0.0; 2]; n],
        conics: vec![[0.0; 4]; n],
        colours: vec![[0.0; 4]; n],
        depths: vec![0.0; n],
        radii: vec![[0; 2]; n],
        tiles_touched: vec![0; n],
    };
    let view = glam::Mat4::from_cols_array_2d(&fp.viewmat);
    let w_rot = Mat3::from_mat4(view);
    let [fx, fy, cx, cy] = fp.intrinsics;
    let (width, height) = (fp.width as f32, fp.height as f32);
    let tan_fovx = 0.5 * width / fx;
    let tan_fovy = 0.5 * height / fy;
    let lim_xp = (width - cx) / fx + 0.3 * tan_fovx;
    let lim_xn = cx / fx + 0.3 * tan_fovx;
    let lim_yp = (height - cy) / fy + 0.3 * tan_fovy;
    let lim_yn = cy / fy + 0.3 * tan_fovy;
    let campos = Vec3::new(fp.campos[0], fp.campos[1], fp.campos[2]);
    let coeffs = fp.sh_coeffs as usize;
    for i in 0..n {
        let mean = Vec3::from(scene.means[i]);
        let t = (view * mean.extend(1.0)).truncate();
        if t.z <= fp.near_plane || t.z > fp.far_plane {
            continue;
        }
        let r = quat_to_mat(scene.quats[i]);
        let s = Vec3::from(scene.scales[i]).exp();
        let m = r * Mat3::from_diagonal(s);
        let v = w_rot * (m * m.transpose()) * w_rot.transpose();
        let rz = 1.0 / t.z;
        let tx = t.z * lim_xp.min((-lim_xn).max(t.x * rz));
        let ty = t.z * lim_yp.min((-lim_yn).max(t.y * rz));
        let j0 = Vec3::new(fx * rz, 0.0, -fx * tx * rz * rz);
        let j1 = Vec3::new(0.0, fy * rz, -fy * ty * rz * rz);
        let a = j0.dot(v * j0) + 0.3;
        let b = j0.dot(v * j1);
        let c = j1.dot(v * j1) + 0.3;
        let det = a * c - b * b;
        if det.is_nan() || det <= 0.0 {
            continue;
        }
        let inv_det = 1.0 / det;
        let opacity = 1.0 / (1.0 + (-scene.opacities[i]).exp());
        if opacity < 1.0 / 255.0 {
            continue;
        }
        let extent = (2.0 * (255.0 * opacity).ln()).sqrt();
        let mid = 0.5 * (a + c);
        let lambda = mid + (mid * mid - det).max(0.1).sqrt();
        let square = (3.0 * lambda.sqrt()).min(1e7);
        let radius = [square.min(extent * a.sqrt()).ceil() as u32, square.min(extent * c.sqrt()).ceil() as u32];
        let xy = [fx * t.x * rz + cx, fy * t.y * rz + cy];
        let (lo, hi) = tile_rect(fp, xy, radius);
        let co = [c * inv_det, -b * inv_det, a * inv_det, opacity];
        let touched = rect_tiles(lo, hi).filter(|&t| splat_hits_tile(xy, co, t)).count() as u32;
        if touched == 0 {
            continue;
        }
        let dir = (mean - campos).normalize();
        let basis = sh_basis(dir, fp.sh_degree);
        let nb = ((fp.sh_degree + 1) * (fp.sh_degree + 1)) as usize;
        let sh = &scene.sh[i * coeffs * 3..];
        let mut rgb = Vec3::ZERO;
        for (k, bk) in basis.iter().enumerate().take(nb) {
            rgb += *bk * Vec3::new(sh[3 * k], sh[3 * k + 1], sh[3 * k + 2]);
        }
        let rgb = (rgb + 0.5).max(Vec3::ZERO);
        p.xys[i] = xy;
        p.conics[i] = co;
        p.colours[i] = [rgb.x, rgb.y, rgb.z, 0.0];
        p.depths[i] = t.z;
        p.radii[i] = radius;
        p.tiles_touched[i] = touched;
    }
    p
}

/// Pass `dispatch_args`: workgroup counts for `n` items, indexed by ARGS_* (one item per
/// thread, radix-sort blocks of `sort_block` keys, scan blocks, the one-dispatch sort, the
/// sort's table scan), clamped to MAX_GROUPS. Up to `sort_small_max` keys the one-dispatch sort
/// runs instead of the sort's passes.
pub fn dispatch_groups(n: u32, sort_block: u32, sort_small_max: u32) -> [u32; 5] {
    let small = n <= sort_small_max;
    [
        n.div_ceil(WG_SIZE),
        if small { 0 } else { n.div_ceil(sort_block) },
        n.div_ceil(SCAN_BLOCK),
        (small && n > 0) as u32,
        (!small) as u32,
    ]
    .map(|g| g.min(MAX_GROUPS))
}

/// Pass `draw_args`: the draw path's VkDrawIndirectCommand for `visible` splats (one instance
/// of QUAD_VERTICES vertices per splat).
pub fn draw_args(visible: u32) -> [u32; 4] {
    [QUAD_VERTICES, visible, 0, 0]
}

/// Exclusive prefix sum and total.
pub fn exclusive_scan(vals: &[u32]) -> (Vec<u32>, u32) {
    let mut acc = 0u32;
    let out = vals
        .iter()
        .map(|v| {
            let r = acc;
            acc += v;
            r
        })
        .collect();
    (out, acc)
}

/// Stable sort of (key, value) pairs by key: what the GPU radix sort must produce.
pub fn stable_sort(keys: &[u32], vals: &[u32]) -> (Vec<u32>, Vec<u32>) {
    let mut pairs: Vec<(u32, u32)> = keys.iter().copied().zip(vals.iter().copied()).collect();
    pairs.sort_by_key(|p| p.0);
    pairs.into_iter().unzip()
}

/// Passes `scan visible`, `compact` and `depth sort`: the visible Gaussians (tiles_touched > 0)
/// in index order, stably sorted by the bits of their depth. Returns (depth keys, ids).
pub fn depth_order(p: &Projected) -> (Vec<u32>, Vec<u32>) {
    let ids: Vec<u32> = (0..p.depths.len() as u32).filter(|&i| p.tiles_touched[i as usize] > 0).collect();
    let keys: Vec<u32> = ids.iter().map(|&i| p.depths[i as usize].to_bits()).collect();
    stable_sort(&keys, &ids)
}

/// Pass `emit`: (tile, Gaussian) pairs of every visible Gaussian in depth order, for the tiles of
/// its rectangle that it reaches (`splat_hits_tile`).
pub fn emit(fp: &FrameParams, p: &Projected, depth_ids: &[u32]) -> (Vec<u32>, Vec<u32>) {
    let mut keys = Vec::new();
    let mut ids = Vec::new();
    for &i in depth_ids {
        let (xy, co) = (p.xys[i as usize], p.conics[i as usize]);
        let (lo, hi) = tile_rect(fp, xy, p.radii[i as usize]);
        for [x, y] in rect_tiles(lo, hi).filter(|&t| splat_hits_tile(xy, co, t)) {
            keys.push(y as u32 * fp.tiles_x + x as u32);
            ids.push(i);
        }
    }
    (keys, ids)
}

/// `splat_reach` (tiles.glsl): half extents in pixels of a splat's alpha >= 1/255 region.
pub fn splat_reach(co: [f32; 4]) -> [f32; 2] {
    let k = (2.0 * (255.0 * co[3]).ln()).max(0.0) / (co[0] * co[2] - co[1] * co[1]).max(1e-30);
    [(k * co[2]).sqrt() * 1.001 + 0.001, (k * co[0]).sqrt() * 1.001 + 0.001]
}

/// `blend_cost` (tiles.glsl): the most loop iterations a splat can cost one blend invocation of
/// tile row `ty` that holds `rows` pixel rows.
pub fn blend_cost(xy: [f32; 2], co: [f32; 4], ty: u32, rows: u32) -> u32 {
    let reach = splat_reach(co)[1];
    let row0 = (ty * TILE_SIZE) as f32 + 0.5;
    let lo = (xy[1] - reach - row0).ceil().clamp(0.0, TILE_SIZE as f32);
    let hi = (xy[1] + reach - row0).floor().clamp(-1.0, TILE_SIZE as f32 - 1.0);
    (hi - lo + 1.0).clamp(1.0, rows as f32) as u32 + 1
}

/// Pass `emit`'s tile costs: per tile, the sum of `blend_cost` over its intersections, with blend
/// invocations of `rows` pixel rows.
pub fn tile_costs(fp: &FrameParams, p: &Projected, depth_ids: &[u32], rows: u32) -> Vec<u32> {
    let mut costs = vec![0u32; (fp.tiles_x * fp.tiles_y) as usize];
    for &i in depth_ids {
        let i = i as usize;
        let (xy, co) = (p.xys[i], p.conics[i]);
        let (lo, hi) = tile_rect(fp, xy, p.radii[i]);
        for [x, y] in rect_tiles(lo, hi).filter(|&t| splat_hits_tile(xy, co, t)) {
            costs[(y as u32 * fp.tiles_x + x as u32) as usize] += blend_cost(xy, co, y as u32, rows);
        }
    }
    costs
}

/// Pass `ranges`: [start, end) of every tile in the tile-sorted intersection keys.
pub fn tile_ranges(keys: &[u32], num_tiles: usize) -> Vec<[u32; 2]> {
    let mut r = vec![[0u32; 2]; num_tiles];
    for (k, &t) in keys.iter().enumerate() {
        if k == 0 || keys[k - 1] != t {
            r[t as usize][0] = k as u32;
        }
        if k + 1 == keys.len() || keys[k + 1] != t {
            r[t as usize][1] = k as u32 + 1;
        }
    }
    r
}

/// Pass `blend`: front-to-back compositing per pixel; rgb = C + T·background, a = T.
pub fn blend(fp: &FrameParams, ranges: &[[u32; 2]], isect_ids: &[u32], p: &Projected) -> Vec<[f32; 4]> {
    let (w, h) = (fp.width as usize, fp.height as usize);
    let bg = Vec3::new(fp.background[0], fp.background[1], fp.background[2]);
    let mut out = vec![[0.0f32; 4]; w * h];
    for py in 0..h {
        for px in 0..w {
            let tile = (py / TILE_SIZE as usize) * fp.tiles_x as usize + px / TILE_SIZE as usize;
            let [start, end] = ranges[tile];
            let pixf = Vec2::new(px as f32 + 0.5, py as f32 + 0.5);
            let mut t = 1.0f32;
            let mut c = Vec3::ZERO;
            for &g in &isect_ids[start as usize..end as usize] {
                let g = g as usize;
                let d = Vec2::from(p.xys[g]) - pixf;
                let co = p.conics[g];
                let power = -0.5 * (co[0] * d.x * d.x + co[2] * d.y * d.y) - co[1] * d.x * d.y;
                if power > 0.0 {
                    continue;
                }
                let alpha = (co[3] * power.exp()).min(0.99);
                if alpha < 1.0 / 255.0 {
                    continue;
                }
                let test_t = t * (1.0 - alpha);
                if test_t < 0.0001 {
                    break;
                }
                c += Vec3::new(p.colours[g][0], p.colours[g][1], p.colours[g][2]) * alpha * t;
                t = test_t;
            }
            let rgb = c + t * bg;
            out[py * w + px] = [rgb.x, rgb.y, rgb.z, t];
        }
    }
    out
}

/// The whole forward pass on the CPU.
pub fn render(scene: &Scene, fp: &FrameParams) -> Vec<[f32; 4]> {
    let p = preprocess(scene, fp);
    let (_, depth_ids) = depth_order(&p);
    let (keys, ids) = emit(fp, &p, &depth_ids);
    let (keys, ids) = stable_sort(&keys, &ids);
    let ranges = tile_ranges(&keys, (fp.tiles_x * fp.tiles_y) as usize);
    blend(fp, &ranges, &ids, &p)
}
