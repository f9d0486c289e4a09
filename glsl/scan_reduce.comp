#version 450
// Reduce-then-scan, pass 1: one sum per block of SCAN_BLOCK items.
#include "common.glsl"
#include "wg_scan.glsl"
#include "scan_input.glsl"
layout(local_size_x = WG_SIZE) in;
layout(std430, binding = 3) writeonly buffer BlockSumsBuf { uint v[]; } block_sums;

void main() {
    uint n = counts.v[args.count_slot];
    uint nblocks = (n + SCAN_BLOCK - 1) / SCAN_BLOCK;
    for (uint b = gl_WorkGroupID.x; b < nblocks; b += gl_NumWorkGroups.x) {
        uint base = b * SCAN_BLOCK + gl_LocalInvocationIndex * SCAN_ITEMS;
        uint sum = 0;
        for (uint k = 0; k < SCAN_ITEMS; k++) {
            if (base + k < n) sum += scan_value(base + k);
        }
        uint total;
        wg_exclusive_add(sum, total);
        if (gl_LocalInvocationIndex == 0) block_sums.v[b] = total;
    }
}
