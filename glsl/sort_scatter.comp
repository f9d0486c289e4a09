#version 450
// Radix sort pass 3: stable scatter. Each thread owns SORT_ITEMS consecutive keys, so ranks
// follow input order: thread t's first slot for digit d is the block's global offset (scanned
// histogram table) plus the counts of d in threads < t.
#include "common.glsl"
#include "wg_scan.glsl"
layout(local_size_x = WG_SIZE) in;
layout(push_constant) uniform Push { SortArgs args; };
layout(std430, binding = 0) readonly buffer CountsBuf { uint v[]; } counts;
layout(std430, binding = 1) readonly buffer KeysInBuf { uint v[]; } keys_in;
layout(std430, binding = 2) readonly buffer ValsInBuf { uint v[]; } vals_in;
layout(std430, binding = 3) readonly buffer HistBuf { uint v[]; } hist;
layout(std430, binding = 4) writeonly buffer KeysOutBuf { uint v[]; } keys_out;
layout(std430, binding = 5) writeonly buffer ValsOutBuf { uint v[]; } vals_out;

// Digit-major per-thread counts: s_off[d * WG_SIZE + t].
shared uint s_off[RADIX_BINS * WG_SIZE];

void main() {
    uint n = counts.v[args.count_slot];
    uint nblocks = (n + SORT_BLOCK - 1) / SORT_BLOCK;
    uint t = gl_LocalInvocationIndex;
    for (uint b = gl_WorkGroupID.x; b < nblocks; b += gl_NumWorkGroups.x) {
        uint base = b * SORT_BLOCK + t * SORT_ITEMS;
        uint h[RADIX_BINS];
        for (uint d = 0; d < RADIX_BINS; d++) h[d] = 0;
        for (uint k = 0; k < SORT_ITEMS; k++) {
            if (base + k < n) h[(keys_in.v[base + k] >> args.shift) & (RADIX_BINS - 1)]++;
        }
        for (uint d = 0; d < RADIX_BINS; d++) s_off[d * WG_SIZE + t] = h[d];
        barrier();
        // Exclusive scan of the flat digit-major table; thread t owns RADIX_BINS entries.
        uint sum = 0;
        for (uint k = 0; k < RADIX_BINS; k++) sum += s_off[t * RADIX_BINS + k];
        uint total;
        uint pre = wg_exclusive_add(sum, total);
        for (uint k = 0; k < RADIX_BINS; k++) {
            uint v = s_off[t * RADIX_BINS + k];
            s_off[t * RADIX_BINS + k] = pre;
            pre += v;
        }
        barrier();
        // The flat scan also counts smaller digits of this block; the global table has them.
        uint pos[RADIX_BINS];
        for (uint d = 0; d < RADIX_BINS; d++) {
            pos[d] = hist.v[d * nblocks + b] + s_off[d * WG_SIZE + t] - s_off[d * WG_SIZE];
        }
        for (uint k = 0; k < SORT_ITEMS; k++) {
            if (base + k < n) {
                uint key = keys_in.v[base + k];
                uint d = (key >> args.shift) & (RADIX_BINS - 1);
                keys_out.v[pos[d]] = key;
                vals_out.v[pos[d]] = vals_in.v[base + k];
                pos[d]++;
            }
        }
        barrier();
    }
}
