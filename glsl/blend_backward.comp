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
// power = -(a dx^2 + c dy^2) / 2 - b dx dy), v_colours and v_splat_opacities (the activated opacity).
// Each invocation sums its pixels, the subgroup sums its invocations, and one lane adds the total
// to the outputs with float atomics (or the CAS fallback, see atomic_add.glsl).
// Each invocation visits only the rows a splat reaches (splat_reach), none where the splat
// misses the subgroup's columns, by the bounds of a loop: lavapipe (Mesa 22.3) skips work only
// by leaving loops; an `if`, uniform or not, merely masks lanes. Specialization constant 3
// (CROWDED_TILES) picks the tiles as in blend: 0 those whose splats fit the loop budget by emit's
// tile_costs, 1 the rest, without that loop (see common.glsl); the rasterizer dispatches both.
#include "common.glsl"
#include "tiles.glsl"
#include "texels.glsl"
#include "atomic_add.glsl"
#extension GL_KHR_shader_subgroup_basic : require
#extension GL_KHR_shader_subgroup_arithmetic : require
#extension GL_KHR_shader_subgroup_vote : require
layout(constant_id = 1) const uint PIXELS_PER_THREAD = 1;
layout(constant_id = 3) const uint CROWDED_TILES = 0;
// Specialization constant 4, as in blend: 1 stages the splats through shared memory in batches
// (GPUs), 0 has every invocation fetch each splat itself and each subgroup walk the tile alone,
// with no shared memory and no barrier (CPU devices).
layout(constant_id = 4) const uint SHARED_BATCHES = 1;
layout(local_size_x = TILE_SIZE, local_size_y_id = 2) in;
#define FRAME_BINDING 0
#include "frame.glsl"
layout(std430, binding = 1) readonly buffer RangesBuf { uvec2 v[]; } ranges;
// The splats' data as texel buffers, as in blend (isect_ids four per texel, xys two).
layout(binding = 2) uniform usamplerBuffer isect_ids;
layout(binding = 3) uniform samplerBuffer xys;
layout(binding = 4) uniform samplerBuffer conics;
layout(binding = 5) uniform samplerBuffer colours;
layout(std430, binding = 6) readonly buffer OutImageBuf { vec4 v[]; } out_image;
layout(std430, binding = 7) readonly buffer LastBuf { uint v[]; } last;
layout(std430, binding = 8) readonly buffer VImageBuf { vec4 v[]; } v_image;
layout(std430, binding = 9) buffer VXysBuf { GRAD_T v[]; } v_xys;
layout(std430, binding = 10) buffer VConicsBuf { GRAD_T v[]; } v_conics;
layout(std430, binding = 11) buffer VColorsBuf { GRAD_T v[]; } v_colours;
layout(std430, binding = 12) buffer VOpacitiesBuf { GRAD_T v[]; } v_splat_opacities;
layout(std430, binding = 13) readonly buffer TileCostsBuf { uint v[]; } tile_costs;

const uint BATCH = TILE_SIZE * TILE_SIZE;
shared vec2 s_xy[BATCH];
shared vec4 s_conic[BATCH];
shared vec3 s_rgb[BATCH];
shared uint s_id[BATCH];
shared uint s_max_last;

// This invocation's pixels (rows py0 + r of column px) and their backward state.
uint px, py0;
float T[PIXELS_PER_THREAD];
float T_final[PIXELS_PER_THREAD];
uint n_last[PIXELS_PER_THREAD];
vec3 v_pix[PIXELS_PER_THREAD];
vec3 behind[PIXELS_PER_THREAD];
vec3 prev_rgb[PIXELS_PER_THREAD];
float prev_alpha[PIXELS_PER_THREAD];
// The subgroup's pixel-centre columns [box_x.x, box_x.y].
vec2 box_x;

// The gradient sums of the splat being processed over this invocation's pixels.
vec2 g_xy;
vec3 g_conic;
vec3 g_rgb;
float g_op;
bool hit;

// Splat number n (1-based in the tile) at row r of this invocation: its gradient added to the
// sums. min_power = ln(1 / (255 o)).
void row_backward(int r, uint n, vec2 xy, vec4 co, vec3 rgb, float min_power) {
    vec2 d = xy - (vec2(px, py0 + r) + 0.5);
    float power = -0.5 * (co.x * d.x * d.x + co.z * d.y * d.y) - co.y * d.x * d.y;
    // alpha >= 1/255 <=> power >= min_power (unless clamped, which needs more): most pixels of a
    // small splat fail this test before the exponential.
    if (n > n_last[r] || power > 0.0 || power < min_power - 1e-4) return;
    float G = exp(power);
    float alpha = min(0.99, co.w * G);
    if (alpha < 1.0 / 255.0) return;
    hit = true;
    T[r] /= 1.0 - alpha;
    g_rgb += alpha * T[r] * v_pix[r];
    behind[r] = prev_alpha[r] * prev_rgb[r] + (1.0 - prev_alpha[r]) * behind[r];
    prev_alpha[r] = alpha;
    prev_rgb[r] = rgb;
    vec3 bg = frame.p.background.rgb;
    float v_alpha = T[r] * dot(rgb - behind[r], v_pix[r]) - T_final[r] / (1.0 - alpha) * dot(bg, v_pix[r]);
    if (co.w * G <= 0.99) {
        float v_G = co.w * v_alpha;
        float gdx = G * d.x, gdy = G * d.y;
        g_xy += v_G * vec2(-gdx * co.x - gdy * co.y, -gdy * co.z - gdx * co.y);
        g_conic += v_G * vec3(-0.5 * gdx * d.x, -gdx * d.y, -0.5 * gdy * d.y);
        g_op += G * v_alpha;
    }
}

// Splat number n (1-based in the tile) of Gaussian g: its gradient over this subgroup's pixels,
// added to the outputs. Workgroup-uniform arguments; call in uniform control flow.
void splat_backward(uint n, uint g, vec2 xy, vec4 co, vec3 rgb) {
    float min_power = log(1.0 / (255.0 * co.w));
    g_xy = vec2(0.0);
    g_conic = vec3(0.0);
    g_rgb = vec3(0.0);
    g_op = 0.0;
    hit = false;
    if (PIXELS_PER_THREAD == 1) {
        // One pixel per invocation (GPUs): row_backward's own test on the power costs less than
        // the reach's log, division and square roots; beyond the reach it returns at once.
        row_backward(0, n, xy, co, rgb, min_power);
    } else {
        vec2 reach = splat_reach(co);
        ivec2 rows = splat_rows(xy.y, reach.y, float(py0) + 0.5, PIXELS_PER_THREAD);
        int r_lo = rows.x;
        int r_hi = xy.x + reach.x < box_x.x || xy.x - reach.x > box_x.y ? -1 : rows.y;
        if (CROWDED_TILES == 0) {
            int r = r_lo;
            do { // max(1, rows) bodies; a `for` would run one more, masked, for its failing test
                if (r <= r_hi) row_backward(min(r, int(PIXELS_PER_THREAD) - 1), n, xy, co, rgb, min_power);
            } while (++r <= r_hi);
        } else {
            for (int r = 0; r < int(PIXELS_PER_THREAD); r++) {
                if (r >= r_lo && r <= r_hi) row_backward(r, n, xy, co, rgb, min_power);
            }
        }
    }
    if (subgroupAny(hit)) {
        g_xy = subgroupAdd(g_xy);
        g_conic = subgroupAdd(g_conic);
        g_rgb = subgroupAdd(g_rgb);
        g_op = subgroupAdd(g_op);
        if (subgroupElect()) {
            ATOMIC_ADD_F(v_xys.v, 2 * g, g_xy.x);
            ATOMIC_ADD_F(v_xys.v, 2 * g + 1, g_xy.y);
            ATOMIC_ADD_F(v_conics.v, 3 * g, g_conic.x);
            ATOMIC_ADD_F(v_conics.v, 3 * g + 1, g_conic.y);
            ATOMIC_ADD_F(v_conics.v, 3 * g + 2, g_conic.z);
            ATOMIC_ADD_F(v_colours.v, 3 * g, g_rgb.x);
            ATOMIC_ADD_F(v_colours.v, 3 * g + 1, g_rgb.y);
            ATOMIC_ADD_F(v_colours.v, 3 * g + 2, g_rgb.z);
            ATOMIC_ADD_F(v_splat_opacities.v, g, g_op);
        }
    }
}

// The q-th splat from the back of the batch (of `count`; none past them), whose tile number is
// first + j + 1 for j = count - 1 - q. Workgroup-uniform arguments.
void backward_batch_splat(uint first, uint q, uint count) {
    if (q < count) {
        uint j = count - 1 - min(q, count - 1);
        splat_backward(first + j + 1, s_id[j], s_xy[j], s_conic[j], s_rgb[j]);
    }
}

// The tile's intersection at index i (none below `first`), fetched by this invocation, as splat
// number i - first + 1. Subgroup-uniform arguments.
void backward_fetched_splat(int i, uint first) {
    if (i >= int(first)) {
        uint g = texel_u32(isect_ids, uint(i));
        splat_backward(uint(i) - first + 1, g, texel_vec2(xys, g), texelFetch(conics, int(g)), texelFetch(colours, int(g)).rgb);
    }
}

void main() {
    load_frame();
    uint tile = gl_WorkGroupID.y * frame.p.tiles_x + gl_WorkGroupID.x;
    px = gl_WorkGroupID.x * TILE_SIZE + gl_LocalInvocationID.x;
    py0 = gl_WorkGroupID.y * TILE_SIZE + gl_LocalInvocationID.y * PIXELS_PER_THREAD;
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
    box_x = vec2(subgroupMin(px), subgroupMax(px)) + 0.5;
    uvec2 range = ranges.v[tile];
    bool mine = (CROWDED_TILES != 0) == blend_tile_crowded(tile_costs.v[tile], range.y - range.x);
    if (SHARED_BATCHES == 0) {
        // Each subgroup alone, from the last splat any of its pixels blended.
        int end = int(range.x + (mine ? subgroupMax(thread_last) : 0));
        if (CROWDED_TILES == 0) {
            for (int i = end - 1; i >= int(range.x); i--) backward_fetched_splat(i, range.x);
        } else {
            // Four splats per iteration (see CROWDED_TILES in common.glsl).
            for (int i = end - 1; i >= int(range.x); i -= 4) {
                backward_fetched_splat(i, range.x);
                backward_fetched_splat(i - 1, range.x);
                backward_fetched_splat(i - 2, range.x);
                backward_fetched_splat(i - 3, range.x);
            }
        }
    } else {
        if (gl_LocalInvocationIndex == 0) s_max_last = 0;
        barrier();
        atomicMax(s_max_last, thread_last);
        barrier();
        uint end = range.x + (mine ? s_max_last : 0);
        uint t = gl_LocalInvocationIndex;
        uint threads = gl_WorkGroupSize.x * gl_WorkGroupSize.y;
        for (uint batch_end = end; batch_end > range.x; batch_end -= min(BATCH, batch_end - range.x)) {
            uint count = min(BATCH, batch_end - range.x);
            uint batch_start = batch_end - count;
            barrier();
            for (uint k = t; k < count; k += threads) {
                uint g = texel_u32(isect_ids, batch_start + k);
                s_id[k] = g;
                s_xy[k] = texel_vec2(xys, g);
                s_conic[k] = texelFetch(conics, int(g));
                s_rgb[k] = texelFetch(colours, int(g)).rgb;
            }
            barrier();
            if (CROWDED_TILES == 0) {
                for (uint jj = count; jj > 0; jj--) {
                    uint j = jj - 1;
                    splat_backward(batch_start - range.x + j + 1, s_id[j], s_xy[j], s_conic[j], s_rgb[j]);
                }
            } else {
                // Four splats per iteration, written out: a quarter of the loop iterations that
                // lavapipe counts (see CROWDED_TILES in common.glsl).
                for (uint q = 0; q < count; q += 4) {
                    backward_batch_splat(batch_start - range.x, q, count);
                    backward_batch_splat(batch_start - range.x, q + 1, count);
                    backward_batch_splat(batch_start - range.x, q + 2, count);
                    backward_batch_splat(batch_start - range.x, q + 3, count);
                }
            }
        }
    }
}
