// Large splats' tiles, tested by a whole subgroup together (preprocess counts them, emit lists
// them). One invocation per splat leaves a subgroup waiting on its largest splat: a splat close
// to the camera spans thousands of tiles while most span a few (on an H100 at 1440x1080, a
// walk-through's preprocess and emit took 2.2 of a 3.4 ms frame). A splat whose tile rectangle
// holds more tiles than the subgroup has lanes is "large": its lane leaves it to these loops,
// where lane k tests the rectangle's tiles k, k + subgroup size, ... in row-major order, so
// emit writes the same intersections in the same order as one invocation would.
// Only subgroup arithmetic (the one subgroup feature the device must have besides basic): a
// lane's value reaches the others through subgroupMax, the next large splat's lane through
// subgroupMin. Call from control flow that is uniform in the subgroup.
// The including kernel declares the specialization constant LARGE_SPLATS_BY_SUBGROUP: 0 turns
// this off (CPU devices: lavapipe runs a subgroup's lanes as one vector, so a lane's long loop
// costs the others no more than the subgroup's shared loops, and the reductions cost extra:
// preprocess and emit took 25 % longer there with it).
#ifndef INSTGS_TILES_SUBGROUP_GLSL
#define INSTGS_TILES_SUBGROUP_GLSL
#extension GL_KHR_shader_subgroup_arithmetic : require
#include "tiles.glsl"

// The number of tiles in the rectangle [lo, hi).
uint rect_tiles(ivec2 lo, ivec2 hi) {
    ivec2 n = max(hi - lo, ivec2(0));
    return uint(n.x) * uint(n.y);
}

// Whether a splat's tile rectangle [lo, hi) is large (tested by its subgroup).
bool rect_is_large(ivec2 lo, ivec2 hi) {
    return LARGE_SPLATS_BY_SUBGROUP != 0 && rect_tiles(lo, hi) > gl_SubgroupSize;
}

// Lane l's value of v, in every lane.
uint from_lane(uint v, uint l) {
    return subgroupMax(gl_SubgroupInvocationID == l ? v : 0u);
}
float from_lane(float v, uint l) {
    return uintBitsToFloat(from_lane(floatBitsToUint(v), l));
}
int from_lane(int v, uint l) {
    return int(from_lane(uint(v), l));
}

// Whether any lane's value of i is below n (the subgroup's loops over its items end together).
bool any_below(uint i, uint n) {
    return (LARGE_SPLATS_BY_SUBGROUP == 0 ? i : subgroupMin(i)) < n;
}

// The lane of the next large splat still to do (`todo`), or NO_LANE once there is none.
const uint NO_LANE = 0xffffffffu;
uint next_lane(bool todo) {
    return LARGE_SPLATS_BY_SUBGROUP == 0 ? NO_LANE : subgroupMin(todo ? gl_SubgroupInvocationID : NO_LANE);
}

// Lane l's large splat (xy, co, tile rectangle [lo, hi)) in every lane.
struct LargeSplat {
    vec2 xy;
    vec4 co;
    ivec2 lo;
    ivec2 hi;
};
LargeSplat large_splat(uint l, vec2 xy, vec4 co, ivec2 lo, ivec2 hi) {
    return LargeSplat(vec2(from_lane(xy.x, l), from_lane(xy.y, l)),
                      vec4(from_lane(co.x, l), from_lane(co.y, l), from_lane(co.z, l), from_lane(co.w, l)),
                      ivec2(from_lane(lo.x, l), from_lane(lo.y, l)), ivec2(from_lane(hi.x, l), from_lane(hi.y, l)));
}

// The tile with row-major number t of the splat's rectangle, and whether the splat reaches it
// (false for t past the rectangle).
bool large_splat_tile(LargeSplat s, uint t, out ivec2 tile) {
    uint w = uint(s.hi.x - s.lo.x);
    tile = s.lo + ivec2(t % w, t / w);
    return t < rect_tiles(s.lo, s.hi) && splat_hits_tile(s.xy, s.co, tile);
}

// The number of tiles each lane's large splat reaches (0 where `large` is false).
uint count_large_splat_tiles(bool large, vec2 xy, vec4 co, ivec2 lo, ivec2 hi) {
    uint touched = 0;
    bool todo = large;
    for (uint l = next_lane(todo); l != NO_LANE; l = next_lane(todo)) {
        LargeSplat s = large_splat(l, xy, co, lo, hi);
        uint area = rect_tiles(s.lo, s.hi);
        uint hits = 0;
        for (uint t = gl_SubgroupInvocationID; t < area; t += gl_SubgroupSize) {
            ivec2 tile;
            hits += large_splat_tile(s, t, tile) ? 1 : 0;
        }
        uint total = subgroupAdd(hits);
        if (gl_SubgroupInvocationID == l) {
            touched = total;
            todo = false;
        }
    }
    return touched;
}
#endif
