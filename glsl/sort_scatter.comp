#version 450
// Radix sort pass 3: stable scatter. Each thread owns SORT_ITEMS consecutive keys, so ranks
// follow input order. With THREAD_RUNS (see sort_count.comp) a thread's first slot for digit d
// is its own column's entry of the scanned table; otherwise it is the block's entry plus the
// count of d in the runs of the block's threads < t (counted again here, through shared memory).
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
layout(std430, binding = 2) readonly buffer ValsInBuf { uint v[]; } vals_in;
layout(std430, binding = 3) readonly buffer HistBuf { uint v[]; } hist;
layout(std430, binding = 4) writeonly buffer KeysOutBuf { uint v[]; } keys_out;
layout(std430, binding = 5) writeonly buffer ValsOutBuf { uint v[]; } vals_out;

shared uint s_cnt[(1 << SORT_BITS_GPU) * SORT_WG]; // [digit][thread]: counts, then first output slots

void main() {
    uint n = counts.v[args.count_slot];
    uint block = WG * SORT_ITEMS;
    uint nblocks = (n + block - 1) / block;
    uint nruns = (n + SORT_ITEMS - 1) / SORT_ITEMS;
    uint bins = 1u << args.bits;
    uint t = gl_LocalInvocationIndex;
    for (uint b = gl_WorkGroupID.x; b < nblocks; b += gl_NumWorkGroups.x) {
        // Private per-thread counters (cheaper than shared memory on lavapipe).
        uint h[MAX_BINS];
        uint base = b * block + t * SORT_ITEMS;
        uint end = min(base + SORT_ITEMS, n);
        if (THREAD_RUNS != 0) {
            // A run past the last one has no keys; it reads the last column harmlessly.
            uint run = min(b * WG + t, nruns - 1);
            for (uint d = 0; d < bins; d++) h[d] = hist.v[d * nruns + run];
        } else {
            for (uint d = 0; d < MAX_BINS; d++) h[d] = 0;
            for (uint idx = base; idx < end; idx++) {
                h[bitfieldExtract(keys_in.v[idx], int(args.shift), int(args.bits))]++;
            }
            for (uint d = 0; d < bins; d++) s_cnt[d * WG + t] = h[d];
            barrier();
            // Thread d turns row d (its digit's counts per thread) into output slots.
            if (t < bins) {
                uint acc = hist.v[t * nblocks + b];
                for (uint j = 0; j < WG; j++) {
                    uint c = s_cnt[t * WG + j];
                    s_cnt[t * WG + j] = acc;
                    acc += c;
                }
            }
            barrier();
            for (uint d = 0; d < bins; d++) h[d] = s_cnt[d * WG + t];
        }
        for (uint idx = base; idx < end; idx++) {
            uint key = keys_in.v[idx];
            uint d = bitfieldExtract(key, int(args.shift), int(args.bits));
            uint p = h[d]++;
            keys_out.v[p] = key;
            vals_out.v[p] = vals_in.v[idx];
        }
        if (THREAD_RUNS == 0) barrier();
    }
}
