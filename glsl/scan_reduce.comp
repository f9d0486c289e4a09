#version 450
// Reduce-then-scan, pass 1: the sum of every column of items, a workgroup's block of
// SCAN_BLOCK items or, with THREAD_RUNS, a thread's run of SCAN_BLOCK / threads items (no
// shared memory or barrier: what CPU devices want, as the radix sort's thread runs).
#include "common.glsl"
#include "wg_scan.glsl"
#include "scan_input.glsl"
// Workgroup size (specialization constant 1): WG_SIZE, or one subgroup with THREAD_RUNS.
layout(local_size_x_id = 1) in;
layout(constant_id = 2) const uint THREAD_RUNS = 0;
const uint WG = gl_WorkGroupSize.x;
// A thread's run with THREAD_RUNS (else SCAN_ITEMS: WG is WG_SIZE, arrays need a literal size).
const uint RUN = SCAN_BLOCK / WG;
layout(std430, binding = 3) writeonly buffer BlockSumsBuf { uint v[]; } block_sums;

void main() {
    uint n = counts.v[args.count_slot];
    uint nblocks = (n + SCAN_BLOCK - 1) / SCAN_BLOCK;
    uint t = gl_LocalInvocationIndex;
    for (uint b = gl_WorkGroupID.x; b < nblocks; b += gl_NumWorkGroups.x) {
        if (THREAD_RUNS != 0) {
            uint base = b * SCAN_BLOCK + t * RUN;
            uint sum = 0;
            for (uint idx = base; idx < min(base + RUN, n); idx++) sum += scan_value(idx);
            if (base < n) block_sums.v[b * WG + t] = sum;
        } else {
            uint base = b * SCAN_BLOCK + t * SCAN_ITEMS;
            uint sum = 0;
            for (uint k = 0; k < SCAN_ITEMS; k++) {
                if (base + k < n) sum += scan_value(base + k);
            }
            uint total;
            wg_exclusive_add(sum, total);
            if (t == 0) block_sums.v[b] = total;
        }
    }
}
