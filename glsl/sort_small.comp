#version 450
// Radix sort of a small input in one dispatch: one workgroup runs every pass (the same digits,
// passes and ping-pong as sort_count / scan_blocks / sort_scatter, so the result lands in the
// same buffer), with its histogram table in shared memory. For up to the policy's
// sort_small_max keys (dispatch_args gives it one workgroup then and the multi-dispatch passes
// none): a pass of the multi-dispatch sort costs three dispatches whatever the input size, which
// on lavapipe is ~0.3 ms (one workgroup is one core, so past ~12 k keys the passes over both
// cores win: BENCHMARKS.md, "The radix sort on CPU devices"). Each thread ranks a run of ceil(n / SORT_SMALL_WG) consecutive keys,
// so the sort is stable.
#include "common.glsl"
layout(local_size_x = SORT_SMALL_WG) in;
layout(push_constant) uniform Push { SortArgs args; }; // args.bits: all key bits (shift unused)
layout(constant_id = 4) const uint MAX_BITS = SORT_BITS_GPU;
const uint MAX_BINS = 1u << MAX_BITS;
const uint WG = SORT_SMALL_WG;
layout(std430, binding = 0) readonly buffer CountsBuf { uint v[]; } counts;
layout(std430, binding = 1) coherent buffer KeysABuf { uint v[]; } keys_a;
layout(std430, binding = 2) coherent buffer ValsABuf { uint v[]; } vals_a;
layout(std430, binding = 3) coherent buffer KeysBBuf { uint v[]; } keys_b;
layout(std430, binding = 4) coherent buffer ValsBBuf { uint v[]; } vals_b;

shared uint s_cnt[MAX_BINS * WG]; // [digit][thread]: counts, then exclusive offsets in the row
shared uint s_row[MAX_BINS]; // each digit's total, then its first output slot

// One pass from (KIN, VIN) to (KOUT, VOUT) on `pass_bits` bits at `shift`.
#define SORT_PASS(KIN, VIN, KOUT, VOUT)                                                          \
    {                                                                                            \
        uint bins = 1u << pass_bits;                                                             \
        uint h[MAX_BINS];                                                                        \
        for (uint d = 0; d < bins; d++) h[d] = 0;                                                \
        for (uint i = base; i < end; i++) h[bitfieldExtract(KIN.v[i], int(shift), int(pass_bits))]++; \
        for (uint d = 0; d < bins; d++) s_cnt[d * WG + t] = h[d];                                \
        barrier();                                                                               \
        for (uint d = t; d < bins; d += WG) {                                                    \
            uint acc = 0;                                                                        \
            for (uint j = 0; j < WG; j++) {                                                      \
                uint c = s_cnt[d * WG + j];                                                      \
                s_cnt[d * WG + j] = acc;                                                         \
                acc += c;                                                                        \
            }                                                                                    \
            s_row[d] = acc;                                                                      \
        }                                                                                        \
        barrier();                                                                               \
        if (t == 0) {                                                                            \
            uint acc = 0;                                                                        \
            for (uint d = 0; d < bins; d++) {                                                    \
                uint c = s_row[d];                                                               \
                s_row[d] = acc;                                                                  \
                acc += c;                                                                        \
            }                                                                                    \
        }                                                                                        \
        barrier();                                                                               \
        for (uint d = 0; d < bins; d++) h[d] = s_row[d] + s_cnt[d * WG + t];                     \
        for (uint i = base; i < end; i++) {                                                      \
            uint key = KIN.v[i];                                                                 \
            uint p = h[bitfieldExtract(key, int(shift), int(pass_bits))]++;                      \
            KOUT.v[p] = key;                                                                     \
            VOUT.v[p] = VIN.v[i];                                                                \
        }                                                                                        \
        memoryBarrierBuffer();                                                                   \
        barrier();                                                                               \
    }

void main() {
    uint n = counts.v[args.count_slot];
    uint t = gl_LocalInvocationIndex;
    uint run = (n + WG - 1) / WG;
    uint base = min(t * run, n);
    uint end = min(base + run, n);
    uint passes = (args.bits + MAX_BITS - 1) / MAX_BITS;
    uint shift = 0;
    // Passes in pairs, a -> b then b -> a; leaving the loop (not an `if`) skips an odd last
    // pass's partner on lavapipe.
    for (uint p = 0; p < passes; p += 2) {
        uint pass_bits = (args.bits - shift + (passes - p) - 1) / (passes - p);
        SORT_PASS(keys_a, vals_a, keys_b, vals_b)
        shift += pass_bits;
        if (p + 1 == passes) break;
        pass_bits = (args.bits - shift + (passes - p - 1) - 1) / (passes - p - 1);
        SORT_PASS(keys_b, vals_b, keys_a, vals_a)
        shift += pass_bits;
    }
}
