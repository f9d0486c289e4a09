#version 450
// Reduce-then-scan, pass 3: exclusive prefix of every item = its block's scanned sum plus the
// prefix inside the block.
#include "common.glsl"
#include "wg_scan.glsl"
#include "scan_input.glsl"
layout(local_size_x = WG_SIZE) in;
layout(std430, binding = 3) readonly buffer BlockSumsBuf { uint v[]; } block_sums;
layout(std430, binding = 4) writeonly buffer ScanOutBuf { uint v[]; } scan_out;

void main() {
    uint n = counts.v[args.count_slot];
    uint nblocks = (n + SCAN_BLOCK - 1) / SCAN_BLOCK;
    for (uint b = gl_WorkGroupID.x; b < nblocks; b += gl_NumWorkGroups.x) {
        uint base = b * SCAN_BLOCK + gl_LocalInvocationIndex * SCAN_ITEMS;
        uint vals[SCAN_ITEMS];
        uint sum = 0;
        for (uint k = 0; k < SCAN_ITEMS; k++) {
            vals[k] = base + k < n ? scan_value(base + k) : 0;
            sum += vals[k];
        }
        uint total;
        uint pre = block_sums.v[b] + wg_exclusive_add(sum, total);
        for (uint k = 0; k < SCAN_ITEMS; k++) {
            if (base + k < n) scan_out.v[base + k] = pre;
            pre += vals[k];
        }
    }
}
