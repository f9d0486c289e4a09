#version 450
// Start and end of every tile's run in the tile-sorted intersection list; tiles without
// intersections keep the (0, 0) the host filled in.
#include "common.glsl"
layout(local_size_x = WG_SIZE) in;
layout(std430, binding = 0) readonly buffer CountsBuf { uint v[]; } counts;
layout(std430, binding = 1) readonly buffer IsectKeysBuf { uint v[]; } isect_keys;
layout(std430, binding = 2) buffer RangesBuf { uvec2 v[]; } ranges;

void main() {
    uint m = counts.v[COUNT_ISECT];
    for (uint k = gl_GlobalInvocationID.x; k < m; k += gl_NumWorkGroups.x * WG_SIZE) {
        uint tile = isect_keys.v[k];
        if (k == 0 || isect_keys.v[k - 1] != tile) ranges.v[tile].x = k;
        if (k == m - 1 || isect_keys.v[k + 1] != tile) ranges.v[tile].y = k + 1;
    }
}
