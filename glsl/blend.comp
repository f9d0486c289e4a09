#version 450
// One workgroup per 16x16 tile, one invocation per pixel: front-to-back alpha blending of the
// tile's depth-sorted Gaussians. As Inria: alpha = min(0.99, o exp(-q/2)), skip alpha < 1/255,
// stop before T drops below 1e-4, and out = C + T * background. The alpha channel of out_image
// holds the final transmittance T.
// Splats reach the pixels in shared-memory batches of 256, and the tile stops early once every
// pixel is saturated.
#include "common.glsl"
layout(local_size_x = TILE_SIZE, local_size_y = TILE_SIZE) in;
layout(std140, binding = 0) uniform FrameBuf { FrameParams p; } frame;
layout(std430, binding = 1) readonly buffer RangesBuf { uvec2 v[]; } ranges;
layout(std430, binding = 2) readonly buffer IsectIdsBuf { uint v[]; } isect_ids;
layout(std430, binding = 3) readonly buffer XysBuf { vec2 v[]; } xys;
layout(std430, binding = 4) readonly buffer ConicsBuf { vec4 v[]; } conics;
layout(std430, binding = 5) readonly buffer ColorsBuf { vec4 v[]; } colors;
layout(std430, binding = 6) writeonly buffer OutImageBuf { vec4 v[]; } out_image;

shared vec2 s_xy[TILE_SIZE * TILE_SIZE];
shared vec4 s_conic[TILE_SIZE * TILE_SIZE];
shared vec3 s_rgb[TILE_SIZE * TILE_SIZE];
shared uint s_done;

// Blends one splat into (C, T); false once the pixel is saturated (T would drop below 1e-4).
bool blend_splat(vec2 xy, vec4 co, vec3 rgb, vec2 pixf, inout float T, inout vec3 C) {
    vec2 d = xy - pixf;
    float power = -0.5 * (co.x * d.x * d.x + co.z * d.y * d.y) - co.y * d.x * d.y;
    if (power > 0.0) return true;
    float alpha = min(0.99, co.w * exp(power));
    if (alpha < 1.0 / 255.0) return true;
    float test_T = T * (1.0 - alpha);
    if (test_T < 0.0001) return false;
    C += rgb * alpha * T;
    T = test_T;
    return true;
}

void main() {
    const uint BATCH = TILE_SIZE * TILE_SIZE;
    uint tile = gl_WorkGroupID.y * frame.p.tiles_x + gl_WorkGroupID.x;
    uvec2 pix = gl_WorkGroupID.xy * TILE_SIZE + gl_LocalInvocationID.xy;
    bool inside = pix.x < frame.p.width && pix.y < frame.p.height;
    vec2 pixf = vec2(pix) + 0.5;
    uvec2 range = ranges.v[tile];
    bool done = !inside;
    float T = 1.0;
    vec3 C = vec3(0.0);
    uint t = gl_LocalInvocationIndex;
    for (uint start = range.x; start < range.y; start += BATCH) {
        if (t == 0) s_done = 0;
        barrier();
        if (done) atomicAdd(s_done, 1);
        barrier();
        if (s_done == BATCH) break;
        if (start + t < range.y) {
            uint g = isect_ids.v[start + t];
            s_xy[t] = xys.v[g];
            s_conic[t] = conics.v[g];
            s_rgb[t] = colors.v[g].rgb;
        }
        barrier();
        uint count = min(BATCH, range.y - start);
        for (uint j = 0; !done && j < count; j++) {
            done = !blend_splat(s_xy[j], s_conic[j], s_rgb[j], pixf, T, C);
        }
        barrier();
    }
    if (inside) out_image.v[pix.y * frame.p.width + pix.x] = vec4(C + T * frame.p.background.rgb, T);
}
