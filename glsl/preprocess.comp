#version 450
// Forward pass 1, one invocation per Gaussian: cull, 3D covariance, EWA projection, conic,
// screen radius, tile rectangle, SH colour and depth. Maths as Inria 3DGS / gsplat:
// Sigma = R S S^T R^T; Sigma2D = J W Sigma W^T J^T + 0.3 I with the Jacobian's x/z, y/z clamped
// to 1.3x the field of view; colour = SH(dir) + 0.5, clamped at 0, dir from the camera centre
// to the world mean. A culled Gaussian gets tiles_touched = 0.
// Screen extent: Inria covers the square of half-width R = 3 sqrt(lambda_max). Alpha reaches
// 1/255 only where q <= e^2, e = sqrt(2 ln(255 o)), i.e. within e sqrt(Sigma_xx) in x and
// e sqrt(Sigma_yy) in y (the ellipse's bounding box, as brush does). The radii are per axis,
// ceil(min(R, e sqrt(Sigma_xx))) and ceil(min(R, e sqrt(Sigma_yy))): blend skips alpha < 1/255,
// so the image is Inria's with fewer empty intersections. Splats with o < 1/255 are culled.
// Instanced splats are expanded first (instance.glsl); nothing expanded is stored. With
// frame.p.select (rendering), instance_select has culled instances and chosen their levels and
// inst_offsets holds the exclusive scan of their splat counts: splat num_background + j is
// Gaussian j - inst_offsets[k] of the level chosen for the instance k whose range holds j.
// The splat count, counts[COUNT_GAUSSIANS], is then GPU-written and this pass is dispatched
// indirectly from it.
#include "common.glsl"
#include "sh.glsl"
// Specialization constant 1: large splats' tiles counted by their subgroup (tiles_subgroup.glsl).
layout(constant_id = 1) const uint LARGE_SPLATS_BY_SUBGROUP = 1;
#include "tiles_subgroup.glsl"
layout(local_size_x = WG_SIZE) in;
#define FRAME_BINDING 0
#include "frame.glsl"
// The parameter rows as RGBA32F texels (read by instance.glsl's expand, through texels.glsl).
layout(binding = 1) uniform samplerBuffer means;
layout(binding = 2) uniform samplerBuffer scales;
layout(binding = 3) uniform samplerBuffer quats;
layout(binding = 4) uniform samplerBuffer opacities;
// The SH rows as RGBA32F texels: lavapipe fetches texels with vector gathers, where a storage
// buffer load is a loop over the lanes (see BENCHMARKS.md, "Texel fetches").
layout(binding = 5) uniform samplerBuffer sh;
layout(std430, binding = 6) writeonly buffer XysBuf { vec2 v[]; } xys;
layout(std430, binding = 7) writeonly buffer ConicsBuf { vec4 v[]; } conics;
layout(std430, binding = 8) writeonly buffer ColorsBuf { vec4 v[]; } colours;
layout(std430, binding = 9) writeonly buffer DepthsBuf { float v[]; } depths;
layout(std430, binding = 10) writeonly buffer RadiiBuf { uvec2 v[]; } radii;
layout(std430, binding = 11) writeonly buffer TilesTouchedBuf { uint v[]; } tiles_touched;
#define INSTANCE_BINDING 12
#include "instance.glsl"
layout(std430, binding = 19) readonly buffer CountsBuf { uint v[]; } counts;
layout(std430, binding = 20) readonly buffer InstOffsetsBuf { uint v[]; } inst_offsets;
layout(std430, binding = 21) readonly buffer InstLevelBuf { uint v[]; } inst_level;

// splat_ref for frame.p.select: the instance by binary search over the scanned counts (the
// last instance whose offset is <= j; empty instances before it share its offset).
SplatRef selected_ref(uint i) {
    if (i < frame.p.num_background) return SplatRef(i, NO_SLOT, NO_SLOT, NO_SLOT);
    uint j = i - frame.p.num_background;
    uint lo = 0, hi = frame.p.num_instances;
    while (hi - lo > 1) {
        uint mid = (lo + hi) / 2;
        if (inst_offsets.v[mid] <= j) lo = mid; else hi = mid;
    }
    uint k = lo;
    uint g = 0;
    while (g + 1 < frame.p.num_groups && k >= groups.v[g + 1].instance_first) g++;
    uint l = inst_level.v[k];
    uint local = j - inst_offsets.v[k];
    uint n = groups.v[g].level_rows[l];
    uint pair = groups.v[g].level_pair_first[l] + (k - groups.v[g].instance_first) * n + local;
    return SplatRef(groups.v[g].level_row_first[l] + local, pair, k, g);
}

// Later passes read nothing else of a culled Gaussian.
void cull(uint i) {
    radii.v[i] = uvec2(0);
    tiles_touched.v[i] = 0;
}

void store(uint i, vec2 xy, vec4 co, vec3 rgb, float depth, uvec2 radius, uint touched) {
    xys.v[i] = xy;
    conics.v[i] = co;
    colours.v[i] = vec4(rgb, 0.0);
    depths.v[i] = depth;
    radii.v[i] = radius;
    tiles_touched.v[i] = touched;
}

// A large splat (tiles_subgroup.glsl), projected and coloured, whose tiles the subgroup counts
// before it is stored (or culled where it reaches none).
bool large;
vec2 large_xy;
vec4 large_co;
ivec2 large_lo, large_hi;
vec3 large_rgb;
float large_depth;
uvec2 large_radius;

void preprocess(uint i) {
    SplatRef ref = frame.p.select != 0 ? selected_ref(i) : splat_ref(i);
    Expanded e = expand(ref);
    vec3 p = e.mean;
    vec3 t = (frame.p.viewmat * vec4(p, 1.0)).xyz;
    if (t.z <= frame.p.near_plane || t.z > frame.p.far_plane) {
        cull(i);
        return;
    }
    mat3 R = quat_to_mat(e.quat / length(e.quat));
    vec3 s = exp(e.log_scale);
    mat3 M = R * mat3(s.x, 0, 0, 0, s.y, 0, 0, 0, s.z);
    mat3 W = mat3(frame.p.viewmat);
    mat3 V = W * (M * transpose(M)) * transpose(W);

    float fx = frame.p.intrinsics.x, fy = frame.p.intrinsics.y;
    float cx = frame.p.intrinsics.z, cy = frame.p.intrinsics.w;
    float tan_fovx = 0.5 * float(frame.p.width) / fx;
    float tan_fovy = 0.5 * float(frame.p.height) / fy;
    float lim_xp = (float(frame.p.width) - cx) / fx + 0.3 * tan_fovx;
    float lim_xn = cx / fx + 0.3 * tan_fovx;
    float lim_yp = (float(frame.p.height) - cy) / fy + 0.3 * tan_fovy;
    float lim_yn = cy / fy + 0.3 * tan_fovy;
    float rz = 1.0 / t.z;
    float tx = t.z * min(lim_xp, max(-lim_xn, t.x * rz));
    float ty = t.z * min(lim_yp, max(-lim_yn, t.y * rz));
    // J rows: (fx/z, 0, -fx tx/z^2), (0, fy/z, -fy ty/z^2)
    vec3 j0 = vec3(fx * rz, 0.0, -fx * tx * rz * rz);
    vec3 j1 = vec3(0.0, fy * rz, -fy * ty * rz * rz);
    vec3 Vj0 = V * j0;
    vec3 Vj1 = V * j1;
    float a = dot(j0, Vj0) + 0.3;
    float b = dot(j0, Vj1);
    float c = dot(j1, Vj1) + 0.3;
    float det = a * c - b * b;
    // Also catches NaN (an overflowing exp(scale)).
    if (!(det > 0.0)) {
        cull(i);
        return;
    }
    float inv_det = 1.0 / det;
    vec3 conic = vec3(c * inv_det, -b * inv_det, a * inv_det);
    float opacity = 1.0 / (1.0 + exp(-e.logit));
    if (opacity < 1.0 / 255.0) {
        cull(i);
        return;
    }
    float extent = sqrt(2.0 * log(255.0 * opacity));
    float mid = 0.5 * (a + c);
    float lambda = mid + sqrt(max(0.1, mid * mid - det));
    // Clamped before the conversion, which is undefined for huge values.
    uvec2 radius = uvec2(ceil(min(vec2(min(3.0 * sqrt(lambda), 1e7)), extent * sqrt(vec2(a, c)))));
    vec2 xy = vec2(fx * t.x * rz + cx, fy * t.y * rz + cy);

    // The tiles of the bounding rectangle that the ellipse reaches (emit lists the same).
    ivec2 rmin, rmax;
    tile_rect(xy, radius, uvec2(frame.p.tiles_x, frame.p.tiles_y), rmin, rmax);
    vec4 co = vec4(conic, opacity);
    uint touched = 0;
    large = rect_is_large(rmin, rmax);
    if (!large) {
        for (int ty = rmin.y; ty < rmax.y; ty++) {
            for (int tx = rmin.x; tx < rmax.x; tx++) touched += splat_hits_tile(xy, co, ivec2(tx, ty)) ? 1 : 0;
        }
        if (touched == 0) {
            cull(i);
            return;
        }
    }

    // SH in template space: direction R^T d.
    vec3 dir = transpose(e.rot) * normalize(p - frame.p.campos.xyz);
    float basis[16];
    sh_basis(dir, frame.p.sh_degree, basis);
    uint nb = (frame.p.sh_degree + 1) * (frame.p.sh_degree + 1);
    vec3 rgb = basis[0] * e.dc;
    // The row's evaluated coefficients in whole vec4s (see sh.glsl): raw[shift + 3k + c].
    uint off = ref.row * frame.p.sh_coeffs * 3;
    uint shift = off & 3;
    float raw[SH_RAW_FLOATS];
    for (uint q = 0; q < (shift + 3 * nb + 3) / 4; q++) {
        vec4 x = texelFetch(sh, int(off / 4 + q));
        raw[4 * q] = x.x;
        raw[4 * q + 1] = x.y;
        raw[4 * q + 2] = x.z;
        raw[4 * q + 3] = x.w;
    }
    for (uint k = 0; k < nb; k++) {
        uint j = shift + 3 * k;
        rgb += basis[k] * vec3(raw[j], raw[j + 1], raw[j + 2]);
    }
    rgb = max(rgb + 0.5, vec3(0.0));

    if (large) {
        large_xy = xy;
        large_co = co;
        large_lo = rmin;
        large_hi = rmax;
        large_rgb = rgb;
        large_depth = t.z;
        large_radius = radius;
        return;
    }
    store(i, xy, co, rgb, t.z, radius, touched);
}

void main() {
    load_frame();
    uint n = counts.v[COUNT_GAUSSIANS];
    // The loop ends for the whole subgroup at once: its lanes count the large splats' tiles
    // together (tiles_subgroup.glsl).
    for (uint i = gl_GlobalInvocationID.x; any_below(i, n); i += gl_NumWorkGroups.x * WG_SIZE) {
        large = false;
        if (i < n) preprocess(i);
        uint touched = count_large_splat_tiles(large, large_xy, large_co, large_lo, large_hi);
        if (large) {
            if (touched == 0) cull(i);
            else store(i, large_xy, large_co, large_rgb, large_depth, large_radius, touched);
        }
    }
}
