#version 450
// Visible Gaussians (tiles_touched > 0) in index order, with their depth bits as sort keys.
// Depth is > near_plane > 0, so the float bits order like the values.
#include "common.glsl"
layout(local_size_x = WG_SIZE) in;
layout(std430, binding = 0) readonly buffer CountsBuf { uint v[]; } counts;
layout(std430, binding = 1) readonly buffer TilesTouchedBuf { uint v[]; } tiles_touched;
layout(std430, binding = 2) readonly buffer VisOffsetsBuf { uint v[]; } vis_offsets;
layout(std430, binding = 3) readonly buffer DepthsBuf { float v[]; } depths;
layout(std430, binding = 4) writeonly buffer DepthKeysBuf { uint v[]; } depth_keys;
layout(std430, binding = 5) writeonly buffer DepthIdsBuf { uint v[]; } depth_ids;

void main() {
    uint n = counts.v[COUNT_GAUSSIANS];
    for (uint i = gl_GlobalInvocationID.x; i < n; i += gl_NumWorkGroups.x * WG_SIZE) {
        if (tiles_touched.v[i] != 0) {
            uint o = vis_offsets.v[i];
            depth_keys.v[o] = floatBitsToUint(depths.v[i]);
            depth_ids.v[o] = i;
        }
    }
}
