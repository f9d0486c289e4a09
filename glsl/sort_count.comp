#version 450
// Radix sort pass 1: per block of SORT_BLOCK keys, the count of each RADIX_BITS digit at
// `shift`, written digit-major (hist[digit * nblocks + block]) so that one exclusive scan of the
// table gives every (digit, block) its global output offset.
#include "common.glsl"
#include "wg_scan.glsl"
layout(local_size_x = WG_SIZE) in;
layout(push_constant) uniform Push { SortArgs args; };
layout(std430, binding = 0) readonly buffer CountsBuf { uint v[]; } counts;
layout(std430, binding = 1) readonly buffer KeysInBuf { uint v[]; } keys_in;
layout(std430, binding = 2) writeonly buffer HistBuf { uint v[]; } hist;

shared uint s_bins[RADIX_BINS];

void main() {
    uint n = counts.v[args.count_slot];
    uint nblocks = (n + SORT_BLOCK - 1) / SORT_BLOCK;
    uint t = gl_LocalInvocationIndex;
    for (uint b = gl_WorkGroupID.x; b < nblocks; b += gl_NumWorkGroups.x) {
        if (t < RADIX_BINS) s_bins[t] = 0;
        barrier();
        uint h[RADIX_BINS];
        for (uint d = 0; d < RADIX_BINS; d++) h[d] = 0;
        uint base = b * SORT_BLOCK + t * SORT_ITEMS;
        for (uint k = 0; k < SORT_ITEMS; k++) {
            if (base + k < n) h[(keys_in.v[base + k] >> args.shift) & (RADIX_BINS - 1)]++;
        }
        for (uint d = 0; d < RADIX_BINS; d++) {
            uint s = subgroupAdd(h[d]);
            if (subgroupElect() && s != 0) atomicAdd(s_bins[d], s);
        }
        barrier();
        if (t < RADIX_BINS) hist.v[t * nblocks + b] = s_bins[t];
        barrier();
    }
}
