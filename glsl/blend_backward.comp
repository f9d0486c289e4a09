#version 450
// Backward of `blend`, one workgroup per tile with the forward's shape (PIXELS_PER_THREAD pixels
// of a tile column per invocation, specialization constants 1 and 2). Every pixel walks the
// tile's splats back to front from its `last` one, recovering T_i = T_(i+1) / (1 - alpha_i) from
// the final T, as Inria 3DGS (backward.cu renderCUDA) and gsplat:
//   dL/dcolor_i = alpha_i T_i dL/dpix
//   dL/dalpha_i = T_i (color_i - S_i) . dL/dpix - T_final / (1 - alpha_i) background . dL/dpix
// where S_i is the colour blended behind splat i. Where alpha hit its 0.99 clamp it carries no
// gradient to the opacity or the 2D Gaussian (gsplat). Outputs are the gradients with respect to
// the preprocess outputs, indexed by Gaussian: v_xys (pixels), v_conics (a, b, c of
// power = -(a dx^2 + c dy^2) / 2 - b dx dy), v_colors and v_opacities (the activated opacity).
// Each invocation sums its pixels, the subgroup sums its invocations, and one lane adds the total
// to the outputs with float atomics (or the CAS fallback, see atomic_add.glsl).
#include "common.glsl"
#include "atomic_add.glsl"
#extension GL_KHR_shader_subgroup_basic : require
#extension GL_KHR_shader_subgroup_arithmetic : require
#extension GL_KHR_shader_subgroup_vote : require
layout(constant_id = 1) const uint PIXELS_PER_THREAD = 1;
layout(local_size_x = TILE_SIZE, local_size_y_id = 2) in;
layout(std430, binding = 0) readonly buffer FrameBuf { FrameParams p; } frame;
layout(std430, binding = 1) readonly buffer RangesBuf { uvec2 v[]; } ranges;
layout(std430, binding = 2) readonly buffer IsectIdsBuf { uint v[]; } isect_ids;
layout(std430, binding = 3) readonly buffer XysBuf { vec2 v[]; } xys;
layout(std430, binding = 4) readonly buffer ConicsBuf { vec4 v[]; } conics;
layout(std430, binding = 5) readonly buffer ColorsBuf { vec4 v[]; } colors;
layout(std430, binding = 6) readonly buffer OutImageBuf { vec4 v[]; } out_image;
layout(std430, binding = 7) readonly buffer LastBuf { uint v[]; } last;
layout(std430, binding = 8) readonly buffer VImageBuf { vec4 v[]; } v_image;
layout(std430, binding = 9) buffer VXysBuf { GRAD_T v[]; } v_xys;
layout(std430, binding = 10) buffer VConicsBuf { GRAD_T v[]; } v_conics;
layout(std430, binding = 11) buffer VColorsBuf { GRAD_T v[]; } v_colors;
layout(std430, binding = 12) buffer VOpacitiesBuf { GRAD_T v[]; } v_opacities;

const uint BATCH = TILE_SIZE * TILE_SIZE;
shared vec2 s_xy[BATCH];
shared vec4 s_conic[BATCH];
shared vec3 s_rgb[BATCH];
shared uint s_id[BATCH];
shared uint s_max_last;

void main() {
    uint tile = gl_WorkGroupID.y * frame.p.tiles_x + gl_WorkGroupID.x;
    uint px = gl_WorkGroupID.x * TILE_SIZE + gl_LocalInvocationID.x;
    uint py0 = gl_WorkGroupID.y * TILE_SIZE + gl_LocalInvocationID.y * PIXELS_PER_THREAD;
    vec3 bg = frame.p.background.rgb;
    float T[PIXELS_PER_THREAD];
    float T_final[PIXELS_PER_THREAD];
    uint n_last[PIXELS_PER_THREAD];
    vec3 v_pix[PIXELS_PER_THREAD];
    vec3 behind[PIXELS_PER_THREAD];
    vec3 prev_rgb[PIXELS_PER_THREAD];
    float prev_alpha[PIXELS_PER_THREAD];
    uint thread_last = 0;
    for (uint r = 0; r < PIXELS_PER_THREAD; r++) {
        bool inside = px < frame.p.width && py0 + r < frame.p.height;
        uint pix = min(py0 + r, frame.p.height - 1) * frame.p.width + min(px, frame.p.width - 1);
        T_final[r] = out_image.v[pix].a;
        T[r] = T_final[r];
        n_last[r] = inside ? last.v[pix] : 0;
        v_pix[r] = v_image.v[pix].rgb;
        behind[r] = vec3(0.0);
        prev_rgb[r] = vec3(0.0);
        prev_alpha[r] = 0.0;
        thread_last = max(thread_last, n_last[r]);
    }
    if (gl_LocalInvocationIndex == 0) s_max_last = 0;
    barrier();
    atomicMax(s_max_last, thread_last);
    barrier();
    uvec2 range = ranges.v[tile];
    uint end = range.x + s_max_last;
    uint t = gl_LocalInvocationIndex;
    uint threads = gl_WorkGroupSize.x * gl_WorkGroupSize.y;
    for (uint batch_end = end; batch_end > range.x; batch_end -= min(BATCH, batch_end - range.x)) {
        uint count = min(BATCH, batch_end - range.x);
        uint batch_start = batch_end - count;
        barrier();
        for (uint k = t; k < count; k += threads) {
            uint g = isect_ids.v[batch_start + k];
            s_id[k] = g;
            s_xy[k] = xys.v[g];
            s_conic[k] = conics.v[g];
            s_rgb[k] = colors.v[g].rgb;
        }
        barrier();
        for (uint jj = count; jj > 0; jj--) {
            uint j = jj - 1;
            uint n = batch_start - range.x + j + 1;
            vec2 xy = s_xy[j];
            vec4 co = s_conic[j];
            vec3 rgb = s_rgb[j];
            // alpha >= 1/255 <=> power >= ln(1 / (255 o)) (unless clamped, which needs more):
            // most pixels of a small splat fail this test before the exponential.
            float min_power = log(1.0 / (255.0 * co.w));
            // Rows of this invocation's column that the splat's alpha >= 1/255 ellipse can reach:
            // |dy| <= sqrt(2 ln(255 o) Sigma_yy), Sigma_yy = a / (a c - b^2) for conic (a, b, c).
            // The bound is the same for every invocation, so the row test below is a uniform
            // branch that skips work for real (lavapipe runs divergent code for all lanes).
            float ry = sqrt(max(-2.0 * min_power, 0.0) * co.x / max(co.x * co.z - co.y * co.y, 1e-30)) + 1.0;
            float row0 = float(PIXELS_PER_THREAD == TILE_SIZE ? gl_WorkGroupID.y * TILE_SIZE : py0) + 0.5;
            vec2 g_xy = vec2(0.0);
            vec3 g_conic = vec3(0.0);
            vec3 g_rgb = vec3(0.0);
            float g_op = 0.0;
            bool hit = false;
            for (uint r = 0; r < PIXELS_PER_THREAD; r++) {
                if (abs(row0 + float(r) - xy.y) > ry) continue;
                vec2 d = xy - (vec2(px, py0 + r) + 0.5);
                float power = -0.5 * (co.x * d.x * d.x + co.z * d.y * d.y) - co.y * d.x * d.y;
                if (n > n_last[r] || power > 0.0 || power < min_power - 1e-4) continue;
                float G = exp(power);
                float alpha = min(0.99, co.w * G);
                if (alpha < 1.0 / 255.0) continue;
                hit = true;
                T[r] /= 1.0 - alpha;
                g_rgb += alpha * T[r] * v_pix[r];
                behind[r] = prev_alpha[r] * prev_rgb[r] + (1.0 - prev_alpha[r]) * behind[r];
                prev_alpha[r] = alpha;
                prev_rgb[r] = rgb;
                float v_alpha = T[r] * dot(rgb - behind[r], v_pix[r]) - T_final[r] / (1.0 - alpha) * dot(bg, v_pix[r]);
                if (co.w * G <= 0.99) {
                    float v_G = co.w * v_alpha;
                    float gdx = G * d.x, gdy = G * d.y;
                    g_xy += v_G * vec2(-gdx * co.x - gdy * co.y, -gdy * co.z - gdx * co.y);
                    g_conic += v_G * vec3(-0.5 * gdx * d.x, -gdx * d.y, -0.5 * gdy * d.y);
                    g_op += G * v_alpha;
                }
            }
            if (subgroupAny(hit)) {
                g_xy = subgroupAdd(g_xy);
                g_conic = subgroupAdd(g_conic);
                g_rgb = subgroupAdd(g_rgb);
                g_op = subgroupAdd(g_op);
                if (subgroupElect()) {
                    uint g = s_id[j];
                    ATOMIC_ADD_F(v_xys.v, 2 * g, g_xy.x);
                    ATOMIC_ADD_F(v_xys.v, 2 * g + 1, g_xy.y);
                    ATOMIC_ADD_F(v_conics.v, 3 * g, g_conic.x);
                    ATOMIC_ADD_F(v_conics.v, 3 * g + 1, g_conic.y);
                    ATOMIC_ADD_F(v_conics.v, 3 * g + 2, g_conic.z);
                    ATOMIC_ADD_F(v_colors.v, 3 * g, g_rgb.x);
                    ATOMIC_ADD_F(v_colors.v, 3 * g + 1, g_rgb.y);
                    ATOMIC_ADD_F(v_colors.v, 3 * g + 2, g_rgb.z);
                    ATOMIC_ADD_F(v_opacities.v, g, g_op);
                }
            }
        }
    }
}
