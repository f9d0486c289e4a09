#version 450
// One invocation per visible Gaussian, in depth order: writes (tile id, Gaussian id) for every
// tile of its rectangle that it reaches (splat_hits_tile, as preprocess counted) at its scanned
// offset. Writes past isect_capacity are dropped; the host
// sees COUNT_ISECT_NEEDED > capacity, grows the buffers and renders again.
// Adds each intersection's blend_cost to its tile's tile_costs (zeroed by the host), with
// blend's PIXELS_PER_THREAD as specialization constant 1. A large splat's tiles are listed by
// its whole subgroup, in the same order (tiles_subgroup.glsl).
#include "common.glsl"
layout(constant_id = 1) const uint PIXELS_PER_THREAD = 1;
// Specialization constant 2: large splats' tiles listed by their subgroup (tiles_subgroup.glsl).
layout(constant_id = 2) const uint LARGE_SPLATS_BY_SUBGROUP = 1;
#include "tiles_subgroup.glsl"
#include "texels.glsl"
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

// Writes intersection o (tile, Gaussian i) unless past the capacity, and adds its cost.
void write_isect(uint o, ivec2 tile_xy, uint i, uint cost) {
    uint tile = uint(tile_xy.y) * frame.p.tiles_x + uint(tile_xy.x);
    if (o < frame.p.isect_capacity) {
        isect_keys.v[o] = tile;
        isect_ids.v[o] = i;
    }
    atomicAdd(tile_costs.v[tile], cost);
}

void main() {
    load_frame();
    uint n = counts.v[COUNT_VISIBLE];
    // The loop ends for the whole subgroup at once: its lanes list the large splats' tiles
    // together.
    for (uint j = gl_GlobalInvocationID.x; any_below(j, n); j += gl_NumWorkGroups.x * WG_SIZE) {
        uint i = j < n ? depth_ids.v[j] : 0;
        vec2 xy = texel_vec2(xys, i);
        uvec2 radius = texel_uvec2(radii, i);
        vec4 co = texelFetch(conics, int(i));
        ivec2 rmin, rmax;
        tile_rect(xy, radius, uvec2(frame.p.tiles_x, frame.p.tiles_y), rmin, rmax);
        uint o = isect_offsets.v[min(j, n - 1)];
        bool large = j < n && rect_is_large(rmin, rmax);
        if (j < n && !large) {
            for (int y = rmin.y; y < rmax.y; y++) {
                uint cost = blend_cost(xy, co, uint(y), PIXELS_PER_THREAD);
                for (int x = rmin.x; x < rmax.x; x++) {
                    if (!splat_hits_tile(xy, co, ivec2(x, y))) continue;
                    write_isect(o, ivec2(x, y), i, cost);
                    o++;
                }
            }
        }
        bool todo = large;
        for (uint l = next_lane(todo); l != NO_LANE; l = next_lane(todo)) {
            LargeSplat s = large_splat(l, xy, co, rmin, rmax);
            uint si = from_lane(i, l);
            uint next = from_lane(o, l);
            uint area = rect_tiles(s.lo, s.hi);
            for (uint t0 = 0; t0 < area; t0 += gl_SubgroupSize) {
                ivec2 tile;
                bool hit = large_splat_tile(s, t0 + gl_SubgroupInvocationID, tile);
                uint before = subgroupExclusiveAdd(hit ? 1u : 0u);
                if (hit) write_isect(next + before, tile, si, blend_cost(s.xy, s.co, uint(tile.y), PIXELS_PER_THREAD));
                next += subgroupAdd(hit ? 1u : 0u);
            }
            if (gl_SubgroupInvocationID == l) todo = false;
        }
    }
}
