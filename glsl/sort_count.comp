#version 450
// Radix sort pass 1: per block of SORT_WG * SORT_ITEMS keys, the count of each digit
// (args.bits bits at args.shift), written digit-major (hist[digit * nblocks + block]) so that one exclusive scan
// of the table gives every (digit, block) its global output offset. Each thread counts its own
// run of keys in a private array (cheaper than shared memory on lavapipe, and no atomics), then
// publishes it as its column of the block's [digit][thread] table.
#include "common.glsl"
layout(local_size_x = SORT_WG) in;
layout(push_constant) uniform Push { SortArgs args; };
layout(constant_id = 1) const uint SORT_ITEMS = SORT_ITEMS_GPU;
layout(std430, binding = 0) readonly buffer CountsBuf { uint v[]; } counts;
layout(std430, binding = 1) readonly buffer KeysInBuf { uint v[]; } keys_in;
layout(std430, binding = 2) writeonly buffer HistBuf { uint v[]; } hist;

shared uint s_cnt[SORT_MAX_BINS * SORT_WG]; // [digit][thread]

void main() {
    uint n = counts.v[args.count_slot];
    uint block = SORT_WG * SORT_ITEMS;
    uint nblocks = (n + block - 1) / block;
    uint bins = 1u << args.bits;
    uint t = gl_LocalInvocationIndex;
    for (uint b = gl_WorkGroupID.x; b < nblocks; b += gl_NumWorkGroups.x) {
        uint h[SORT_MAX_BINS];
        for (uint d = 0; d < SORT_MAX_BINS; d++) h[d] = 0;
        uint base = b * block + t * SORT_ITEMS;
        uint end = min(base + SORT_ITEMS, n);
        for (uint idx = base; idx < end; idx++) {
            uint d = bitfieldExtract(keys_in.v[idx], int(args.shift), int(args.bits));
            h[d]++;
        }
        for (uint d = 0; d < bins; d++) s_cnt[d * SORT_WG + t] = h[d];
        barrier();
        if (t < bins) {
            uint sum = 0;
            for (uint j = 0; j < SORT_WG; j++) sum += s_cnt[t * SORT_WG + j];
            hist.v[t * nblocks + b] = sum;
        }
        barrier();
    }
}
