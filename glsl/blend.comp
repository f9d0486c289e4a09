#version 450
// One workgroup per 16x16 tile: front-to-back alpha blending of the tile's depth-sorted
// Gaussians. As Inria: alpha = min(0.99, o exp(-q/2)), skip alpha < 1/255, stop before T drops
// below 1e-4, and out = C + T * background. The alpha channel of out_image holds the final T and
// `last` the number of the tile's splats up to and including the pixel's last blended one (where
// the backward pass starts).
// Splats reach the pixels in shared-memory batches of 256; the tile stops early once every
// pixel is saturated.
// Each invocation blends PIXELS_PER_THREAD pixels of one tile column (specialization constant
// 1; the workgroup is TILE_SIZE x TILE_SIZE / PIXELS_PER_THREAD, constant 2). GPUs use 1. On CPU
// devices every load costs far more than arithmetic (lavapipe loads per lane), so one load of a
// splat serves many pixels there.
#include "common.glsl"
layout(constant_id = 1) const uint PIXELS_PER_THREAD = 1;
layout(local_size_x = TILE_SIZE, local_size_y_id = 2) in;
layout(std430, binding = 0) readonly buffer FrameBuf { FrameParams p; } frame;
layout(std430, binding = 1) readonly buffer RangesBuf { uvec2 v[]; } ranges;
layout(std430, binding = 2) readonly buffer IsectIdsBuf { uint v[]; } isect_ids;
layout(std430, binding = 3) readonly buffer XysBuf { vec2 v[]; } xys;
layout(std430, binding = 4) readonly buffer ConicsBuf { vec4 v[]; } conics;
layout(std430, binding = 5) readonly buffer ColorsBuf { vec4 v[]; } colors;
layout(std430, binding = 6) writeonly buffer OutImageBuf { vec4 v[]; } out_image;
layout(std430, binding = 7) writeonly buffer LastBuf { uint v[]; } last;

const uint BATCH = TILE_SIZE * TILE_SIZE;
shared vec2 s_xy[BATCH];
shared vec4 s_conic[BATCH];
shared vec3 s_rgb[BATCH];
shared uint s_done;

// Blends splat number n (1-based in the tile) into (C, T, n_last), without branches; false once
// the pixel is saturated (T would drop below 1e-4), in which case (C, T, n_last) stay as they were.
bool blend_splat(vec2 xy, vec4 co, vec3 rgb, vec2 pixf, uint n, inout float T, inout vec3 C, inout uint n_last) {
    vec2 d = xy - pixf;
    float power = -0.5 * (co.x * d.x * d.x + co.z * d.y * d.y) - co.y * d.x * d.y;
    float alpha = min(0.99, co.w * exp(power));
    float test_T = T * (1.0 - alpha);
    bool used = power <= 0.0 && alpha >= 1.0 / 255.0;
    bool saturated = used && test_T < 0.0001;
    bool add = used && !saturated;
    C += rgb * (add ? alpha * T : 0.0);
    T = add ? test_T : T;
    n_last = add ? n : n_last;
    return !saturated;
}

void main() {
    uint threads = gl_WorkGroupSize.x * gl_WorkGroupSize.y;
    uint tile = gl_WorkGroupID.y * frame.p.tiles_x + gl_WorkGroupID.x;
    uint px = gl_WorkGroupID.x * TILE_SIZE + gl_LocalInvocationID.x;
    uint py0 = gl_WorkGroupID.y * TILE_SIZE + gl_LocalInvocationID.y * PIXELS_PER_THREAD;
    float T[PIXELS_PER_THREAD];
    vec3 C[PIXELS_PER_THREAD];
    uint n_last[PIXELS_PER_THREAD];
    bool done[PIXELS_PER_THREAD];
    bool thread_done = true;
    for (uint r = 0; r < PIXELS_PER_THREAD; r++) {
        T[r] = 1.0;
        C[r] = vec3(0.0);
        n_last[r] = 0;
        done[r] = px >= frame.p.width || py0 + r >= frame.p.height;
        thread_done = thread_done && done[r];
    }
    uvec2 range = ranges.v[tile];
    uint t = gl_LocalInvocationIndex;
    float row0 = float(PIXELS_PER_THREAD == TILE_SIZE ? gl_WorkGroupID.y * TILE_SIZE : py0) + 0.5;
    for (uint start = range.x; start < range.y; start += BATCH) {
        if (t == 0) s_done = 0;
        barrier();
        if (thread_done) atomicAdd(s_done, 1);
        barrier();
        if (s_done == threads) break;
        for (uint k = t; k < BATCH && start + k < range.y; k += threads) {
            uint g = isect_ids.v[start + k];
            s_xy[k] = xys.v[g];
            s_conic[k] = conics.v[g];
            s_rgb[k] = colors.v[g].rgb;
        }
        barrier();
        uint count = min(BATCH, range.y - start);
        for (uint j = 0; !thread_done && j < count; j++) {
            vec2 xy = s_xy[j];
            vec4 co = s_conic[j];
            vec3 rgb = s_rgb[j];
            // Rows the splat's alpha >= 1/255 ellipse can reach (|dy| <= sqrt(2 ln(255 o)
            // Sigma_yy), plus a pixel): a workgroup-uniform test on CPU devices, where lavapipe
            // then really skips the other rows (a per-lane test would not: lanes run in lock step).
            float ry = sqrt(max(2.0 * log(255.0 * co.w), 0.0) * co.x / max(co.x * co.z - co.y * co.y, 1e-30)) + 1.0;
            thread_done = true;
            for (uint r = 0; r < PIXELS_PER_THREAD; r++) {
                if (!done[r] && abs(row0 + float(r) - xy.y) <= ry) {
                    vec2 pixf = vec2(px, py0 + r) + 0.5;
                    done[r] = !blend_splat(xy, co, rgb, pixf, start - range.x + j + 1, T[r], C[r], n_last[r]);
                }
                thread_done = thread_done && done[r];
            }
        }
        barrier();
    }
    for (uint r = 0; r < PIXELS_PER_THREAD; r++) {
        if (px < frame.p.width && py0 + r < frame.p.height) {
            uint pix = (py0 + r) * frame.p.width + px;
            out_image.v[pix] = vec4(C[r] + T[r] * frame.p.background.rgb, T[r]);
            last.v[pix] = n_last[r];
        }
    }
}
