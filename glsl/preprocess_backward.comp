#version 450
// Backward of `preprocess`, one invocation per parameter row: from the gradients with respect to
// the projected splats (v_xys, v_conics, v_colours, v_splat_opacities, written by blend_backward) to
// the gradients of the scene parameters: v_means, v_scales (log), v_quats (raw, before
// normalisation), v_opacities (logit) and v_sh (every stored coefficient; zero above the
// evaluated degree). Culled splats pass no gradient. Maths as Inria's backward.cu and gsplat's
// VJPs, except that the Jacobian clamp is differentiated exactly (a clamped x/z passes no
// gradient to t.x, and d/dz follows the clamped value) and the SH colour passes gradient to the
// mean through the view direction.
// Instancing (paper Eq. 7-9): a template row loops over its group's K instances, computes each
// expanded splat's gradient g_ik, writes the offset gradients 1:1 (v_d_means = dL/dmean,
// v_d_sh0 = dL/dDC, v_d_opacities = dL/dlogit, which includes the sigmoid's derivative)
// and sums J_k^T g_ik into the template's gradient in registers: means s R^T, log-scales 1,
// quaternions q_T^-1 * (the transpose of left multiplication by the unit q_T), logit 1, SH 1
// (the direction is already in template space). No atomics: a row owns its sums.
// With frame.p.xform_grads, every pair also writes its instance-transform gradient terms
// (XFORM_GRAD_TERMS; summed per instance by xform_grad_reduce): dL/dt = g_mean, dL/d ln s =
// g_mean . (s R mean_t) + sum g_logscale, dL/dR = s g_mean mean_t^T + d g_dir_t^T (mean and the
// template-space SH direction d_t = R^T d), dL/dq_R = g_quat * conj(q_t) (composition).
// With frame.p.tile_cost_weight = w > 0 (training's frame-cost regulariser), every visible splat
// adds w x its tiles touched to the gradient of each of its three log-scales: the gradient of
// R = w sum_splats sg(tiles_touched) (ln s_x + ln s_y + ln s_z), the tile count held constant
// (sg). It shrinks the splats that touch many tiles, whose blend work is the frame's largest
// share on lavapipe. A template Gaussian sums it over its drawn copies, as every other term.
// With CAMERA_GRADS (specialization constant 2, with VISIBLE_ROWS: training's camera refinement of
// a plain scene), each workgroup also sums its visible splats' camera-gradient terms (registers,
// then a shared-memory tree) and writes them at terms[workgroup * CAMERA_GRAD_TERMS..] (summed by
// camera_grad_reduce): dL/dW = v_t p^T + 2 v_V W Sigma and dL/dt = v_t for viewmat = [W | t]
// (t_cam = W p + t, V = W Sigma W^T), and dL/dcampos = -(v_dir - dir (dir . v_dir)) / |p - campos|.
// Densification statistics of visible splats: grad2d_accum += |v_xy| in Inria's NDC units
// (pixels scaled by width/2, height/2), grad2d_count += 1, max_radii = max(max_radii, radius).
// VISIBLE_ROWS (specialization constant 1, plain scenes only): one invocation per visible
// Gaussian of the frame (its depth-sorted visible ids, frame.p.num_visible of them, copied there
// from counts on the GPU); the host zeroes the gradients first. lavapipe spends as much on a culled row as on a visible one (an `if`
// only masks lanes), and a training view sees 35-50 % of ducks6's Gaussians.
#include "common.glsl"
#include "sh.glsl"
layout(local_size_x = WG_SIZE) in;
#define FRAME_BINDING 0
#include "frame.glsl"
// The parameter rows as RGBA32F texels (read by instance.glsl's expand, through texels.glsl).
layout(binding = 1) uniform samplerBuffer means;
layout(binding = 2) uniform samplerBuffer scales;
layout(binding = 3) uniform samplerBuffer quats;
layout(binding = 4) uniform samplerBuffer opacities;
layout(std430, binding = 5) readonly buffer ShBuf { vec4 v[]; } sh;
layout(std430, binding = 6) readonly buffer RadiiBuf { uvec2 v[]; } radii;
layout(std430, binding = 7) readonly buffer TilesTouchedBuf { uint v[]; } tiles_touched;
layout(std430, binding = 8) readonly buffer VXysBuf { vec2 v[]; } v_xys;
layout(std430, binding = 9) readonly buffer VConicsBuf { float v[]; } v_conics;
layout(std430, binding = 10) readonly buffer VColorsBuf { float v[]; } v_colours;
layout(std430, binding = 11) readonly buffer VOpacitiesBuf { float v[]; } v_splat_opacities;
layout(std430, binding = 12) writeonly buffer GradMeansBuf { float v[]; } v_means;
layout(std430, binding = 13) writeonly buffer GradScalesBuf { float v[]; } v_scales;
layout(std430, binding = 14) writeonly buffer GradQuatsBuf { vec4 v[]; } v_quats;
layout(std430, binding = 15) writeonly buffer GradOpacitiesBuf { float v[]; } v_opacities;
layout(std430, binding = 16) writeonly buffer GradShBuf { vec4 v[]; } v_sh;
layout(std430, binding = 17) buffer Grad2dAccumBuf { float v[]; } grad2d_accum;
layout(std430, binding = 18) buffer Grad2dCountBuf { uint v[]; } grad2d_count;
layout(std430, binding = 19) buffer MaxRadiiBuf { uint v[]; } max_radii;
layout(std430, binding = 20) writeonly buffer GradDMeansBuf { float v[]; } v_d_means;
layout(std430, binding = 21) writeonly buffer GradDSh0Buf { float v[]; } v_d_sh0;
layout(std430, binding = 22) writeonly buffer GradDOpacitiesBuf { float v[]; } v_d_opacities;
// The per-pair transform terms (instanced scenes) or the per-visible-splat camera terms (plain).
layout(std430, binding = 30) writeonly buffer TermsBuf { float v[]; } terms;
layout(std430, binding = 31) readonly buffer VisibleIdsBuf { uint v[]; } visible_ids;
layout(constant_id = 1) const uint VISIBLE_ROWS = 0;
layout(constant_id = 2) const uint CAMERA_GRADS = 0;
#define INSTANCE_BINDING 23
#include "instance.glsl"

// dL/dSH of the row being processed, (coefficient, channel) at 3k + c, summed over its splats
// in registers and written once (lavapipe stores lane by lane).
float acc_sh[48];
// The invocation's sum of its splats' camera-gradient terms (with CAMERA_GRADS).
float acc_camera[CAMERA_GRAD_TERMS];
shared float camera_partial[CAMERA_GRAD_TERMS][WG_SIZE];

// Gradient of one expanded splat i (row, expansion e) with respect to its expanded parameters;
// dL/dSH (every evaluated coefficient) is added to acc_sh. Returns false when culled.
// With CAMERA_GRADS, the splat's camera-gradient terms are added to acc_camera.
bool splat_backward(uint i, uint row, Expanded e, out vec3 v_p, out vec3 v_ls, out vec4 v_q, out float v_logit,
                    out vec3 v_dc, out vec3 dir, out vec3 v_dir_t) {
    if (tiles_touched.v[i] == 0) return false;
    vec3 p = e.mean;
    mat3 W = mat3(frame.p.viewmat);
    vec3 t = (frame.p.viewmat * vec4(p, 1.0)).xyz;
    vec4 q_raw = e.quat;
    float q_len = length(q_raw);
    vec4 q = q_raw / q_len;
    float w = q.x, x = q.y, y = q.z, z = q.w;
    mat3 R = quat_to_mat(q);
    vec3 s = exp(e.log_scale);
    mat3 M = R * mat3(s.x, 0, 0, 0, s.y, 0, 0, 0, s.z);
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
    float ux = t.x * rz, uy = t.y * rz;
    float cux = min(lim_xp, max(-lim_xn, ux));
    float cuy = min(lim_yp, max(-lim_yn, uy));
    bool free_x = ux == cux, free_y = uy == cuy;
    vec3 j0 = vec3(fx * rz, 0.0, -fx * cux * rz);
    vec3 j1 = vec3(0.0, fy * rz, -fy * cuy * rz);
    vec3 Vj0 = V * j0;
    vec3 Vj1 = V * j1;
    float a = dot(j0, Vj0) + 0.3;
    float b = dot(j0, Vj1);
    float c = dot(j1, Vj1) + 0.3;
    float inv_det = 1.0 / (a * c - b * b);

    // Conic (A, B, C) = (c, -b, a) / det is the inverse of Sigma2 = [[a, b], [b, c]].
    vec3 vc = vec3(v_conics.v[3 * i], v_conics.v[3 * i + 1], v_conics.v[3 * i + 2]);
    mat2 Q = mat2(c, -b, -b, a) * inv_det;
    mat2 Gq = mat2(vc.x, 0.5 * vc.y, 0.5 * vc.y, vc.z);
    mat2 Gs = -(Q * Gq * Q);
    float va = Gs[0][0], vb = Gs[0][1] + Gs[1][0], vcc = Gs[1][1];

    // Sigma2 = J V J^T + 0.3 I.
    mat3 v_V = va * outerProduct(j0, j0) + 0.5 * vb * (outerProduct(j0, j1) + outerProduct(j1, j0)) +
               vcc * outerProduct(j1, j1);
    vec3 v_j0 = 2.0 * va * Vj0 + vb * Vj1;
    vec3 v_j1 = vb * Vj0 + 2.0 * vcc * Vj1;
    vec3 v_t = vec3(0.0);
    // j0 = (fx / z, 0, -fx u / z), u = clamp(t.x / z).
    float dux_dtx = free_x ? rz : 0.0, dux_dz = free_x ? -t.x * rz * rz : 0.0;
    float duy_dty = free_y ? rz : 0.0, duy_dz = free_y ? -t.y * rz * rz : 0.0;
    v_t.x += v_j0.z * (-fx * rz) * dux_dtx;
    v_t.y += v_j1.z * (-fy * rz) * duy_dty;
    v_t.z += v_j0.x * (-fx * rz * rz) + v_j0.z * (fx * cux * rz * rz - fx * rz * dux_dz);
    v_t.z += v_j1.y * (-fy * rz * rz) + v_j1.z * (fy * cuy * rz * rz - fy * rz * duy_dz);
    // xy = (fx t.x / z + cx, fy t.y / z + cy).
    vec2 vxy = v_xys.v[i];
    v_t.x += vxy.x * fx * rz;
    v_t.y += vxy.y * fy * rz;
    v_t.z -= (vxy.x * fx * t.x + vxy.y * fy * t.y) * rz * rz;

    // V = W Sigma W^T, Sigma = M M^T, M = R diag(s).
    mat3 v_Sigma = transpose(W) * v_V * W;
    mat3 v_M = 2.0 * v_Sigma * M;
    vec3 v_s = vec3(dot(v_M[0], R[0]), dot(v_M[1], R[1]), dot(v_M[2], R[2]));
    mat3 v_R = v_M * mat3(s.x, 0, 0, 0, s.y, 0, 0, 0, s.z);
    // G[row][col] = v_R[col][row] (GLSL matrices are column-major).
    float g00 = v_R[0][0], g01 = v_R[1][0], g02 = v_R[2][0];
    float g10 = v_R[0][1], g11 = v_R[1][1], g12 = v_R[2][1];
    float g20 = v_R[0][2], g21 = v_R[1][2], g22 = v_R[2][2];
    v_q = 2.0 * vec4(-z * g01 + y * g02 + z * g10 - x * g12 - y * g20 + x * g21,
                     y * g01 + z * g02 + y * g10 - 2.0 * x * g11 - w * g12 + z * g20 + w * g21 - 2.0 * x * g22,
                     -2.0 * y * g00 + x * g01 + w * g02 + x * g10 + z * g12 - w * g20 + z * g21 - 2.0 * y * g22,
                     -2.0 * z * g00 - w * g01 + x * g02 + w * g10 - 2.0 * z * g11 + y * g12 + x * g20 + y * g21);
    v_q = (v_q - q * dot(q, v_q)) / q_len;

    // Colour: rgb = max(SH(R^T dir) + 0.5, 0), dir = normalize(p - campos); DC + offset.
    vec3 dv = p - frame.p.campos.xyz;
    float dv_len = length(dv);
    dir = dv / dv_len;
    vec3 dir_t = transpose(e.rot) * dir;
    float basis[16];
    vec3 dbasis[16];
    sh_basis(dir_t, frame.p.sh_degree, basis);
    sh_basis_grad(dir_t, frame.p.sh_degree, dbasis);
    uint nb = (frame.p.sh_degree + 1) * (frame.p.sh_degree + 1);
    // The row's evaluated coefficients in whole vec4s (see sh.glsl): raw[shift + 3k + c].
    uint off = row * frame.p.sh_coeffs * 3;
    uint shift = off & 3;
    float raw[SH_RAW_FLOATS];
    for (uint q = 0; q < (shift + 3 * nb + 3) / 4; q++) {
        vec4 x = sh.v[off / 4 + q];
        raw[4 * q] = x.x;
        raw[4 * q + 1] = x.y;
        raw[4 * q + 2] = x.z;
        raw[4 * q + 3] = x.w;
    }
    vec3 coef[16];
    vec3 rgb = basis[0] * e.dc;
    for (uint k = 0; k < nb; k++) {
        uint j = shift + 3 * k;
        coef[k] = vec3(raw[j], raw[j + 1], raw[j + 2]);
        rgb += basis[k] * coef[k];
    }
    rgb += 0.5;
    vec3 v_rgb = vec3(v_colours.v[3 * i], v_colours.v[3 * i + 1], v_colours.v[3 * i + 2]);
    v_rgb *= vec3(greaterThan(rgb, vec3(0.0)));
    v_dir_t = vec3(0.0);
    for (uint k = 0; k < nb; k++) {
        acc_sh[3 * k] += basis[k] * v_rgb.x;
        acc_sh[3 * k + 1] += basis[k] * v_rgb.y;
        acc_sh[3 * k + 2] += basis[k] * v_rgb.z;
        v_dir_t += dot(coef[k], v_rgb) * dbasis[k];
    }
    vec3 v_dir = e.rot * v_dir_t;
    vec3 v_dir_p = (v_dir - dir * dot(dir, v_dir)) / dv_len;
    v_p = transpose(W) * v_t + v_dir_p;
    if (CAMERA_GRADS != 0) {
        mat3 v_W = outerProduct(v_t, p) + 2.0 * v_V * W * (M * transpose(M));
        for (uint c = 0; c < 3; c++) {
            acc_camera[3 * c] += v_W[c].x;
            acc_camera[3 * c + 1] += v_W[c].y;
            acc_camera[3 * c + 2] += v_W[c].z;
            acc_camera[9 + c] += v_t[c];
            acc_camera[12 + c] -= v_dir_p[c];
        }
    }
    // Plus the frame-cost regulariser's w x tiles touched (see the header).
    v_ls = v_s * s + vec3(frame.p.tile_cost_weight * float(tiles_touched.v[i]));
    v_dc = basis[0] * v_rgb;
    float o = 1.0 / (1.0 + exp(-e.logit));
    v_logit = v_splat_opacities.v[i] * o * (1.0 - o);

    grad2d_accum.v[i] += length(vxy * vec2(0.5 * float(frame.p.width), 0.5 * float(frame.p.height)));
    grad2d_count.v[i] += 1;
    uvec2 rad = radii.v[i];
    max_radii.v[i] = max(max_radii.v[i], max(rad.x, rad.y));
    return true;
}

// Row r: a background Gaussian (one splat) or a template Gaussian (K splats).
void backward(uint r) {
    for (uint k = 0; k < 48; k++) acc_sh[k] = 0.0;
    vec3 gm = vec3(0.0), gs = vec3(0.0);
    vec4 gq = vec4(0.0);
    float go = 0.0;
    uint first = r, count = 1, stride = 0;
    if (r >= frame.p.num_background) {
        uint g = 0;
        while (g + 1 < frame.p.num_groups && r >= groups.v[g + 1].row_first) g++;
        uint j = r - groups.v[g].row_first;
        first = groups.v[g].splat_first + j;
        count = groups.v[g].instances;
        stride = groups.v[g].rows;
    }
    for (uint k = 0; k < count; k++) {
        uint i = first + k * stride;
        SplatRef ref = splat_ref(i);
        Expanded e = expand(ref);
        vec3 v_p, v_ls, v_dc, dir, v_dir_t;
        vec4 v_q;
        float v_logit;
        bool seen = splat_backward(i, r, e, v_p, v_ls, v_q, v_logit, v_dc, dir, v_dir_t);
        if (!seen) {
            v_p = vec3(0.0);
            v_ls = vec3(0.0);
            v_q = vec4(0.0);
            v_logit = 0.0;
            v_dc = vec3(0.0);
            v_dir_t = vec3(0.0);
        }
        if (ref.pair == NO_SLOT) {
            gm = v_p;
            gs = v_ls;
            gq = v_q;
            go = v_logit;
        } else {
            uint p = ref.pair;
            v_d_means.v[3 * p] = v_p.x;
            v_d_means.v[3 * p + 1] = v_p.y;
            v_d_means.v[3 * p + 2] = v_p.z;
            v_d_sh0.v[3 * p] = v_dc.x;
            v_d_sh0.v[3 * p + 1] = v_dc.y;
            v_d_sh0.v[3 * p + 2] = v_dc.z;
            v_d_opacities.v[p] = v_logit;
            InstanceXform x = xforms.v[ref.xform];
            if (frame.p.xform_grads != 0) {
                vec3 m_t = texel_vec3(means, 3 * r);
                mat3 v_R = x.scale.x * outerProduct(v_p, m_t) + outerProduct(dir, v_dir_t);
                vec4 q_t = texelFetch(quats, int(r));
                vec4 v_qr = quat_mul(v_q, q_t * vec4(1.0, -1.0, -1.0, -1.0));
                uint o = p * XFORM_GRAD_TERMS;
                terms.v[o] = v_p.x;
                terms.v[o + 1] = v_p.y;
                terms.v[o + 2] = v_p.z;
                terms.v[o + 3] = dot(v_p, mat3(x.transform) * m_t) + v_ls.x + v_ls.y + v_ls.z;
                for (uint c = 0; c < 3; c++) {
                    terms.v[o + 4 + 3 * c] = v_R[c].x;
                    terms.v[o + 5 + 3 * c] = v_R[c].y;
                    terms.v[o + 6 + 3 * c] = v_R[c].z;
                }
                terms.v[o + 13] = v_qr.x;
                terms.v[o + 14] = v_qr.y;
                terms.v[o + 15] = v_qr.z;
                terms.v[o + 16] = v_qr.w;
            }
            gm += transpose(mat3(x.transform)) * v_p;
            gs += v_ls;
            gq += quat_mul(x.quat * vec4(1.0, -1.0, -1.0, -1.0), v_q);
            go += v_logit;
        }
    }
    v_means.v[3 * r] = gm.x;
    v_means.v[3 * r + 1] = gm.y;
    v_means.v[3 * r + 2] = gm.z;
    v_scales.v[3 * r] = gs.x;
    v_scales.v[3 * r + 1] = gs.y;
    v_scales.v[3 * r + 2] = gs.z;
    v_quats.v[r] = gq;
    v_opacities.v[r] = go;
    // Every stored coefficient of the row (zero above the evaluated degree): the whole vec4s,
    // and before and after them the floats of vec4s shared with the neighbouring rows.
    uint n = frame.p.sh_coeffs * 3;
    uint off = r * n;
    uint head = min((4 - (off & 3)) & 3, n);
    uint quads = (n - head) / 4;
    for (uint j = 0; j < head; j++) v_sh.v[(off + j) / 4][(off + j) & 3] = acc_sh[j];
    for (uint q = 0; q < quads; q++) {
        uint j = head + 4 * q;
        v_sh.v[(off + j) / 4] = vec4(acc_sh[j], acc_sh[j + 1], acc_sh[j + 2], acc_sh[j + 3]);
    }
    for (uint j = head + 4 * quads; j < n; j++) v_sh.v[(off + j) / 4][(off + j) & 3] = acc_sh[j];
}

void main() {
    load_frame();
    for (uint c = 0; c < CAMERA_GRAD_TERMS; c++) acc_camera[c] = 0.0;
    uint rows = VISIBLE_ROWS != 0 ? frame.p.num_visible : frame.p.num_rows;
    for (uint j = gl_GlobalInvocationID.x; j < rows; j += gl_NumWorkGroups.x * WG_SIZE) {
        backward(VISIBLE_ROWS != 0 ? visible_ids.v[j] : j);
    }
    // The workgroup's camera-gradient terms.
    if (CAMERA_GRADS != 0) {
        uint lid = gl_LocalInvocationID.x;
        for (uint c = 0; c < CAMERA_GRAD_TERMS; c++) camera_partial[c][lid] = acc_camera[c];
        barrier();
        for (uint w = WG_SIZE / 2; w > 0; w /= 2) {
            if (lid < w) {
                for (uint c = 0; c < CAMERA_GRAD_TERMS; c++) camera_partial[c][lid] += camera_partial[c][lid + w];
            }
            barrier();
        }
        if (lid < CAMERA_GRAD_TERMS) terms.v[gl_WorkGroupID.x * CAMERA_GRAD_TERMS + lid] = camera_partial[lid][0];
    }
}
