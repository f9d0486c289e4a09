#version 450
// One invocation per visible Gaussian, in depth order: writes (tile id, Gaussian id) for every
// tile of its rectangle at its scanned offset. Writes past isect_capacity are dropped; the host
// sees COUNT_ISECT_NEEDED > capacity, grows the buffers and renders again.
#include "common.glsl"
#include "tiles.glsl"
layout(local_size_x = WG_SIZE) in;
layout(std430, binding = 0) readonly buffer FrameBuf { FrameParams p; } frame;
layout(std430, binding = 1) readonly buffer CountsBuf { uint v[]; } counts;
layout(std430, binding = 2) readonly buffer DepthIdsBuf { uint v[]; } depth_ids;
layout(std430, binding = 3) readonly buffer IsectOffsetsBuf { uint v[]; } isect_offsets;
layout(std430, binding = 4) readonly buffer XysBuf { vec2 v[]; } xys;
layout(std430, binding = 5) readonly buffer RadiiBuf { uvec2 v[]; } radii;
layout(std430, binding = 6) writeonly buffer IsectKeysBuf { uint v[]; } isect_keys;
layout(std430, binding = 7) writeonly buffer IsectIdsBuf { uint v[]; } isect_ids;

void main() {
    uint n = counts.v[COUNT_VISIBLE];
    for (uint j = gl_GlobalInvocationID.x; j < n; j += gl_NumWorkGroups.x * WG_SIZE) {
        uint i = depth_ids.v[j];
        ivec2 rmin, rmax;
        tile_rect(xys.v[i], radii.v[i], uvec2(frame.p.tiles_x, frame.p.tiles_y), rmin, rmax);
        uint o = isect_offsets.v[j];
        for (int y = rmin.y; y < rmax.y; y++) {
            for (int x = rmin.x; x < rmax.x; x++) {
                if (o < frame.p.isect_capacity) {
                    isect_keys.v[o] = uint(y) * frame.p.tiles_x + uint(x);
                    isect_ids.v[o] = i;
                }
                o++;
            }
        }
    }
}
