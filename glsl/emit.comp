#version 450
// One invocation per visible Gaussian, in depth order: writes (tile id, Gaussian id) for every
// tile of its rectangle that it reaches (splat_hits_tile, as preprocess counted) at its scanned
// offset. Writes past isect_capacity are dropped; the host
// sees COUNT_ISECT_NEEDED > capacity, grows the buffers and renders again.
// Adds each intersection's blend_cost to its tile's tile_costs (zeroed by the host), with
// blend's PIXELS_PER_THREAD as specialization constant 1.
#include "common.glsl"
#include "tiles.glsl"
#include "texels.glsl"
layout(constant_id = 1) const uint PIXELS_PER_THREAD = 1;
layout(local_size_x = WG_SIZE) in;
#define FRAME_BINDING 0
#include "frame.glsl"
layout(std430, binding = 1) readonly buffer CountsBuf { uint v[]; } counts;
layout(std430, binding = 2) readonly buffer DepthIdsBuf { uint v[]; } depth_ids;
layout(std430, binding = 3) readonly buffer IsectOffsetsBuf { uint v[]; } isect_offsets;
// The splats' projections as texels (xys and radii two splats per texel, conics one): one
// gather each on lavapipe (see frame.glsl).
layout(binding = 4) uniform samplerBuffer xys;
layout(binding = 5) uniform usamplerBuffer radii;
layout(std430, binding = 6) writeonly buffer IsectKeysBuf { uint v[]; } isect_keys;
layout(std430, binding = 7) writeonly buffer IsectIdsBuf { uint v[]; } isect_ids;
layout(binding = 8) uniform samplerBuffer conics;
layout(std430, binding = 9) buffer TileCostsBuf { uint v[]; } tile_costs;

void main() {
    load_frame();
    uint n = counts.v[COUNT_VISIBLE];
    for (uint j = gl_GlobalInvocationID.x; j < n; j += gl_NumWorkGroups.x * WG_SIZE) {
        uint i = depth_ids.v[j];
        vec2 xy = texel_vec2(xys, i);
        uvec2 radius = texel_uvec2(radii, i);
        vec4 co = texelFetch(conics, int(i));
        ivec2 rmin, rmax;
        tile_rect(xy, radius, uvec2(frame.p.tiles_x, frame.p.tiles_y), rmin, rmax);
        uint o = isect_offsets.v[j];
        for (int y = rmin.y; y < rmax.y; y++) {
            uint cost = blend_cost(xy, co, uint(y), PIXELS_PER_THREAD);
            for (int x = rmin.x; x < rmax.x; x++) {
                if (!splat_hits_tile(xy, co, ivec2(x, y))) continue;
                uint tile = uint(y) * frame.p.tiles_x + uint(x);
                if (o < frame.p.isect_capacity) {
                    isect_keys.v[o] = tile;
                    isect_ids.v[o] = i;
                }
                atomicAdd(tile_costs.v[tile], cost);
                o++;
            }
        }
    }
}
