#version 450
// Radix sort pass 1: count each digit (args.bits bits at args.shift) per histogram column,
// written digit-major (hist[digit * columns + column]) so that one exclusive scan of the table
// gives every (digit, column) its global output offset. Each thread counts its own run of
// SORT_ITEMS consecutive keys in a private array (cheaper than shared memory on lavapipe, and
// no atomics). With THREAD_RUNS each run is its own column (no shared memory, no barrier: what
// CPU devices want); otherwise a column is a workgroup's block of runs, summed through
// shared memory (fewer columns to scan: what GPUs want).
#include "common.glsl"
// Workgroup size (specialization constant 3): SORT_WG, or one subgroup with THREAD_RUNS.
layout(local_size_x_id = 3) in;
layout(push_constant) uniform Push { SortArgs args; };
layout(constant_id = 1) const uint SORT_ITEMS = SORT_ITEMS_GPU;
layout(constant_id = 2) const uint THREAD_RUNS = 0;
layout(constant_id = 4) const uint MAX_BITS = SORT_BITS_GPU;
const uint MAX_BINS = 1u << MAX_BITS;
const uint WG = gl_WorkGroupSize.x;
layout(std430, binding = 0) readonly buffer CountsBuf { uint v[]; } counts;
layout(std430, binding = 1) readonly buffer KeysInBuf { uint v[]; } keys_in;
layout(std430, binding = 2) writeonly buffer HistBuf { uint v[]; } hist;

shared uint s_cnt[(1 << SORT_BITS_GPU) * SORT_WG]; // [digit][thread]

void main() {
    uint n = counts.v[args.count_slot];
    uint block = WG * SORT_ITEMS;
    uint nblocks = (n + block - 1) / block;
    uint nruns = (n + SORT_ITEMS - 1) / SORT_ITEMS;
    uint bins = 1u << args.bits;
    uint t = gl_LocalInvocationIndex;
    for (uint b = gl_WorkGroupID.x; b < nblocks; b += gl_NumWorkGroups.x) {
        uint h[MAX_BINS];
        for (uint d = 0; d < MAX_BINS; d++) h[d] = 0;
        uint base = b * block + t * SORT_ITEMS;
        uint end = min(base + SORT_ITEMS, n);
        for (uint idx = base; idx < end; idx++) {
            uint d = bitfieldExtract(keys_in.v[idx], int(args.shift), int(args.bits));
            h[d]++;
        }
        if (THREAD_RUNS != 0) {
            uint run = b * WG + t;
            if (run < nruns) {
                for (uint d = 0; d < bins; d++) hist.v[d * nruns + run] = h[d];
            }
        } else {
            for (uint d = 0; d < bins; d++) s_cnt[d * WG + t] = h[d];
            barrier();
            if (t < bins) {
                uint sum = 0;
                for (uint j = 0; j < WG; j++) sum += s_cnt[t * WG + j];
                hist.v[t * nblocks + b] = sum;
            }
            barrier();
        }
    }
}
