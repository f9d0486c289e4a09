#version 450
// Reduce-then-scan, pass 2: one workgroup scans `data` in place (exclusive), where
// len = ceil(counts[count_slot] / divisor) * multiplier. Used for the block sums of the generic
// scan and for the radix sort's digit-major histogram table. Writes the total to counts.
#include "common.glsl"
#include "wg_scan.glsl"
layout(local_size_x = WG_SIZE) in;
layout(push_constant) uniform Push { ScanArgs args; };
layout(std430, binding = 0) buffer CountsBuf { uint v[]; } counts;
layout(std430, binding = 1) buffer DataBuf { uint v[]; } data;

void main() {
    uint n = counts.v[args.count_slot];
    uint len = (n + args.divisor - 1) / args.divisor * args.multiplier;
    uint carry = 0;
    for (uint start = 0; start < len; start += SCAN_BLOCK) {
        uint base = start + gl_LocalInvocationIndex * SCAN_ITEMS;
        uint vals[SCAN_ITEMS];
        uint sum = 0;
        for (uint k = 0; k < SCAN_ITEMS; k++) {
            vals[k] = base + k < len ? data.v[base + k] : 0;
            sum += vals[k];
        }
        uint total;
        uint pre = carry + wg_exclusive_add(sum, total);
        for (uint k = 0; k < SCAN_ITEMS; k++) {
            if (base + k < len) data.v[base + k] = pre;
            pre += vals[k];
        }
        carry += total;
    }
    if (gl_LocalInvocationIndex == 0) {
        if (args.out_slot != NO_SLOT) counts.v[args.out_slot] = carry + args.out_bias;
        if (args.clamp_slot != NO_SLOT) counts.v[args.clamp_slot] = min(carry + args.out_bias, args.capacity);
    }
}
