#version 450
// One workgroup per 16x16 tile: front-to-back alpha blending of the tile's depth-sorted
// Gaussians. As Inria: alpha = min(0.99, o exp(-q/2)), skip alpha < 1/255, stop before T drops
// below 1e-4, and out = C + T * background. The alpha channel of out_image holds the final T and
// `last` the number of the tile's splats up to and including the pixel's last blended one (where
// the backward pass starts).
// Each invocation blends PIXELS_PER_THREAD pixels of one tile column (specialization constant
// 1; the workgroup is TILE_SIZE x TILE_SIZE / PIXELS_PER_THREAD, constant 2). GPUs use 1. On CPU
// devices every load costs far more than arithmetic (lavapipe loads per lane), so one load of a
// splat serves many pixels there, and each invocation visits only the rows a splat reaches
// (splat_reach), none where it misses the subgroup's columns, by the bounds of a loop: lavapipe
// (Mesa 22.3) skips work only by leaving loops; an `if`, uniform or not, merely masks lanes.
// Specialization constant 3 (CROWDED_TILES) picks the tiles: 0 those whose splats fit the loop
// budget by emit's tile_costs, 1 the rest, without that loop (see common.glsl); the rasterizer
// dispatches both.
// On GPUs splats reach the pixels in shared-memory batches of 256 (SHARED_BATCHES) and the
// tile stops early once every pixel is saturated; on CPU devices each invocation fetches every
// splat itself and stops once its own pixels are.
#include "common.glsl"
#include "tiles.glsl"
#include "texels.glsl"
#extension GL_KHR_shader_subgroup_arithmetic : require
layout(constant_id = 1) const uint PIXELS_PER_THREAD = 1;
layout(constant_id = 3) const uint CROWDED_TILES = 0;
// Specialization constant 4: 1 stages the splats through shared memory in batches (GPUs), 0
// has every invocation fetch each splat itself, with no shared memory and no barrier (CPU
// devices: a shared-memory load is a loop over the lanes there, a texel fetch a gather).
layout(constant_id = 4) const uint SHARED_BATCHES = 1;
layout(local_size_x = TILE_SIZE, local_size_y_id = 2) in;
#define FRAME_BINDING 0
#include "frame.glsl"
layout(std430, binding = 1) readonly buffer RangesBuf { uvec2 v[]; } ranges;
// The splats' data as texel buffers (isect_ids four per texel, xys two): lavapipe fetches texels with
// vector gathers, where a storage-buffer load is a loop over the lanes.
layout(binding = 2) uniform usamplerBuffer isect_ids;
layout(binding = 3) uniform samplerBuffer xys;
layout(binding = 4) uniform samplerBuffer conics;
layout(binding = 5) uniform samplerBuffer colours;
layout(std430, binding = 6) writeonly buffer OutImageBuf { vec4 v[]; } out_image;
layout(std430, binding = 7) writeonly buffer LastBuf { uint v[]; } last;
layout(std430, binding = 8) readonly buffer TileCostsBuf { uint v[]; } tile_costs;

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

// This invocation's pixels (rows py0 + r of column px) and their blending state.
uint px, py0;
float T[PIXELS_PER_THREAD];
vec3 C[PIXELS_PER_THREAD];
uint n_last[PIXELS_PER_THREAD];
uint done_rows; // bit r: row r is saturated or outside the image
uint n_done; // rows of this invocation that are done
// The subgroup's pixel-centre columns [box_x.x, box_x.y].
vec2 box_x;

// Blends splat number n (1-based in the tile) into row r of this invocation unless it is done.
void blend_row(int r, uint n, vec2 xy, vec4 co, vec3 rgb) {
    if ((done_rows & (1u << r)) == 0 && !blend_splat(xy, co, rgb, vec2(px, py0 + r) + 0.5, n, T[r], C[r], n_last[r])) {
        done_rows |= 1u << r;
        n_done++;
    }
}

// Blends splat number n (1-based in the tile) into this invocation's pixels that it reaches.
// One pixel per invocation (GPUs): blended without the reach test, whose log, division and
// square roots cost more than the pixel; beyond the reach alpha < 1/255 and the pixel is
// unchanged either way.
void blend_rows(uint n, vec2 xy, vec4 co, vec3 rgb) {
    if (PIXELS_PER_THREAD == 1) {
        blend_row(0, n, xy, co, rgb);
        return;
    }
    vec2 reach = splat_reach(co);
    ivec2 rows = splat_rows(xy.y, reach.y, float(py0) + 0.5, PIXELS_PER_THREAD);
    int r_lo = rows.x;
    int r_hi = xy.x + reach.x < box_x.x || xy.x - reach.x > box_x.y ? -1 : rows.y;
    if (CROWDED_TILES == 0) {
        int r = r_lo;
        do { // max(1, rows) bodies; a `for` would run one more, masked, for its failing test
            if (r <= r_hi) blend_row(min(r, int(PIXELS_PER_THREAD) - 1), n, xy, co, rgb);
        } while (++r <= r_hi);
    } else {
        for (int r = 0; r < int(PIXELS_PER_THREAD); r++) {
            if (r >= r_lo && r <= r_hi) blend_row(r, n, xy, co, rgb);
        }
    }
}

// Blends the batch's splat j (of `count`; none past them) whose tile number is first + j + 1.
void blend_batch_splat(uint first, uint j, uint count) {
    if (j < count) {
        uint b = min(j, BATCH - 1);
        vec4 co = s_conic[b];
        blend_rows(first + j + 1, s_xy[b], co, s_rgb[b]);
    }
}

// Blends the tile's intersection at index i (none at or past `end`), fetched by this
// invocation, as splat number i - first + 1.
void blend_fetched_splat(uint i, uint first, uint end) {
    if (i < end) {
        uint g = texel_u32(isect_ids, i);
        vec4 co = texelFetch(conics, int(g));
        blend_rows(i - first + 1, texel_vec2(xys, g), co, texelFetch(colours, int(g)).rgb);
    }
}

void main() {
    load_frame();
    uint threads = gl_WorkGroupSize.x * gl_WorkGroupSize.y;
    uint tile = gl_WorkGroupID.y * frame.p.tiles_x + gl_WorkGroupID.x;
    px = gl_WorkGroupID.x * TILE_SIZE + gl_LocalInvocationID.x;
    py0 = gl_WorkGroupID.y * TILE_SIZE + gl_LocalInvocationID.y * PIXELS_PER_THREAD;
    n_done = 0;
    done_rows = 0;
    for (uint r = 0; r < PIXELS_PER_THREAD; r++) {
        T[r] = 1.0;
        C[r] = vec3(0.0);
        n_last[r] = 0;
        if (px >= frame.p.width || py0 + r >= frame.p.height) {
            done_rows |= 1u << r;
            n_done++;
        }
    }
    box_x = vec2(subgroupMin(px), subgroupMax(px)) + 0.5;
    uvec2 range = ranges.v[tile];
    bool mine = (CROWDED_TILES != 0) == blend_tile_crowded(tile_costs.v[tile], range.y - range.x);
    if (!mine) range.y = range.x;
    bool thread_done = n_done == PIXELS_PER_THREAD;
    uint t = gl_LocalInvocationIndex;
    if (SHARED_BATCHES == 0) {
        if (CROWDED_TILES == 0) {
            for (uint i = range.x; !thread_done && i < range.y; i++) {
                blend_fetched_splat(i, range.x, range.y);
                thread_done = n_done == PIXELS_PER_THREAD;
            }
        } else {
            for (uint i = range.x; !thread_done && i < range.y; i += 4) {
                blend_fetched_splat(i, range.x, range.y);
                blend_fetched_splat(i + 1, range.x, range.y);
                blend_fetched_splat(i + 2, range.x, range.y);
                blend_fetched_splat(i + 3, range.x, range.y);
                thread_done = n_done == PIXELS_PER_THREAD;
            }
        }
    } else {
        for (uint start = range.x; start < range.y; start += BATCH) {
            if (t == 0) s_done = 0;
            barrier();
            if (thread_done) atomicAdd(s_done, 1);
            barrier();
            if (s_done == threads) break;
            for (uint k = t; k < BATCH && start + k < range.y; k += threads) {
                uint g = texel_u32(isect_ids, start + k);
                s_xy[k] = texel_vec2(xys, g);
                s_conic[k] = texelFetch(conics, int(g));
                s_rgb[k] = texelFetch(colours, int(g)).rgb;
            }
            barrier();
            uint count = min(BATCH, range.y - start);
            if (CROWDED_TILES == 0) {
                for (uint j = 0; !thread_done && j < count; j++) {
                    vec4 co = s_conic[j];
                    blend_rows(start - range.x + j + 1, s_xy[j], co, s_rgb[j]);
                    thread_done = n_done == PIXELS_PER_THREAD;
                }
            } else {
                // Four splats per iteration, written out: a quarter of the loop iterations that
                // lavapipe counts (see CROWDED_TILES in common.glsl).
                for (uint j = 0; !thread_done && j < count; j += 4) {
                    blend_batch_splat(start - range.x, j, count);
                    blend_batch_splat(start - range.x, j + 1, count);
                    blend_batch_splat(start - range.x, j + 2, count);
                    blend_batch_splat(start - range.x, j + 3, count);
                    thread_done = n_done == PIXELS_PER_THREAD;
                }
            }
            barrier();
        }
    }
    for (uint r = 0; r < PIXELS_PER_THREAD; r++) {
        if (mine && px < frame.p.width && py0 + r < frame.p.height) {
            uint pix = (py0 + r) * frame.p.width + px;
            out_image.v[pix] = vec4(C[r] + T[r] * frame.p.background.rgb, T[r]);
            last.v[pix] = n_last[r];
        }
    }
}
