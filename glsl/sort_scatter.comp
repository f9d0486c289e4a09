#version 450
// Radix sort pass 3: stable scatter. Each thread owns SORT_ITEMS consecutive keys, so ranks
// follow input order: thread t's first slot for digit d is the block's global offset for d
// (from the scanned histogram table) plus the count of d in the runs of threads < t.
#include "common.glsl"
layout(local_size_x = SORT_WG) in;
layout(push_constant) uniform Push { SortArgs args; };
layout(constant_id = 1) const uint SORT_ITEMS = SORT_ITEMS_GPU;
layout(std430, binding = 0) readonly buffer CountsBuf { uint v[]; } counts;
layout(std430, binding = 1) readonly buffer KeysInBuf { uint v[]; } keys_in;
layout(std430, binding = 2) readonly buffer ValsInBuf { uint v[]; } vals_in;
layout(std430, binding = 3) readonly buffer HistBuf { uint v[]; } hist;
layout(std430, binding = 4) writeonly buffer KeysOutBuf { uint v[]; } keys_out;
layout(std430, binding = 5) writeonly buffer ValsOutBuf { uint v[]; } vals_out;

shared uint s_cnt[SORT_MAX_BINS * SORT_WG]; // [digit][thread]: counts, then first output slots

void main() {
    uint n = counts.v[args.count_slot];
    uint block = SORT_WG * SORT_ITEMS;
    uint nblocks = (n + block - 1) / block;
    uint bins = 1u << args.bits;
    uint t = gl_LocalInvocationIndex;
    for (uint b = gl_WorkGroupID.x; b < nblocks; b += gl_NumWorkGroups.x) {
        // Private per-thread counters (cheaper than shared memory on lavapipe).
        uint h[SORT_MAX_BINS];
        for (uint d = 0; d < SORT_MAX_BINS; d++) h[d] = 0;
        uint base = b * block + t * SORT_ITEMS;
        uint end = min(base + SORT_ITEMS, n);
        for (uint idx = base; idx < end; idx++) {
            h[bitfieldExtract(keys_in.v[idx], int(args.shift), int(args.bits))]++;
        }
        for (uint d = 0; d < bins; d++) s_cnt[d * SORT_WG + t] = h[d];
        barrier();
        // Thread d turns row d (its digit's counts per thread) into output slots.
        if (t < bins) {
            uint acc = hist.v[t * nblocks + b];
            for (uint j = 0; j < SORT_WG; j++) {
                uint c = s_cnt[t * SORT_WG + j];
                s_cnt[t * SORT_WG + j] = acc;
                acc += c;
            }
        }
        barrier();
        for (uint d = 0; d < bins; d++) h[d] = s_cnt[d * SORT_WG + t];
        for (uint idx = base; idx < end; idx++) {
            uint key = keys_in.v[idx];
            uint d = bitfieldExtract(key, int(args.shift), int(args.bits));
            uint p = h[d]++;
            keys_out.v[p] = key;
            vals_out.v[p] = vals_in.v[idx];
        }
        barrier();
    }
}
