#version 450
// Reduce-then-scan, pass 3: exclusive prefix of every item = its column's scanned sum plus the
// prefix inside the column (columns as in scan_reduce.comp).
#include "common.glsl"
#include "wg_scan.glsl"
#include "scan_input.glsl"
// Workgroup size (specialization constant 1): WG_SIZE, or one subgroup with THREAD_RUNS.
layout(local_size_x_id = 1) in;
layout(constant_id = 2) const uint THREAD_RUNS = 0;
const uint WG = gl_WorkGroupSize.x;
// A thread's run with THREAD_RUNS (else SCAN_ITEMS: WG is WG_SIZE, arrays need a literal size).
const uint RUN = SCAN_BLOCK / WG;
layout(std430, binding = 3) readonly buffer BlockSumsBuf { uint v[]; } block_sums;
layout(std430, binding = 4) writeonly buffer ScanOutBuf { uint v[]; } scan_out;

void main() {
    uint n = counts.v[args.count_slot];
    uint nblocks = (n + SCAN_BLOCK - 1) / SCAN_BLOCK;
    uint t = gl_LocalInvocationIndex;
    for (uint b = gl_WorkGroupID.x; b < nblocks; b += gl_NumWorkGroups.x) {
        if (THREAD_RUNS != 0) {
            uint base = b * SCAN_BLOCK + t * RUN;
            // A run past the last one has no items; it reads the last column harmlessly.
            uint pre = block_sums.v[min(b * WG + t, (n + RUN - 1) / RUN - 1)];
            for (uint idx = base; idx < min(base + RUN, n); idx++) {
                uint v = scan_value(idx);
                scan_out.v[idx] = pre;
                pre += v;
            }
        } else {
            uint base = b * SCAN_BLOCK + t * SCAN_ITEMS;
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
}
