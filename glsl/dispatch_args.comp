#version 450
// Writes the VkDispatchIndirectCommand entries of one count slot from the GPU-written count, so
// later passes are sized without a CPU read-back. Kernels loop grid-stride past MAX_GROUPS.
#include "common.glsl"
layout(local_size_x = 1) in;
layout(push_constant) uniform Push { DispatchArgs args; };
layout(std430, binding = 0) readonly buffer CountsBuf { uint v[]; } counts;
layout(std430, binding = 1) writeonly buffer IndirectBuf { uint v[]; } indirect;

void put(uint kind, uint groups) {
    uint at = (args.count_slot * ARGS_PER_SLOT + kind) * 3;
    indirect.v[at] = min(groups, MAX_GROUPS);
    indirect.v[at + 1] = 1;
    indirect.v[at + 2] = 1;
}

void main() {
    uint n = counts.v[args.count_slot];
    put(ARGS_ITEMS, (n + WG_SIZE - 1) / WG_SIZE);
    // A sort of at most sort_small_max keys is one workgroup of sort_small; a larger one is
    // the multi-dispatch passes (their blocks and their one-workgroup table scan).
    bool small = n <= args.sort_small_max;
    put(ARGS_SORT_BLOCKS, small ? 0 : (n + args.sort_block - 1) / args.sort_block);
    put(ARGS_SCAN_BLOCKS, (n + SCAN_BLOCK - 1) / SCAN_BLOCK);
    put(ARGS_SORT_SMALL, small && n > 0 ? 1 : 0);
    put(ARGS_SORT_SCAN, small ? 0 : 1);
}
