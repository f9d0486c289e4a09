#version 450
// Instance-transform gradients: one workgroup per instance sums its pairs' XFORM_GRAD_TERMS
// terms (written by preprocess_backward) over the instance's template Gaussians, per-thread
// partial sums then a shared-memory tree: no atomics, a fixed order (deterministic).
#include "common.glsl"
layout(local_size_x = WG_SIZE) in;
#define FRAME_BINDING 0
#include "frame.glsl"
layout(std430, binding = 1) readonly buffer GroupsBuf { GroupInfo v[]; } groups;
layout(std430, binding = 2) readonly buffer TermsBuf { float v[]; } terms;
layout(std430, binding = 3) writeonly buffer GradXformsBuf { float v[]; } v_xforms;

shared float partial[WG_SIZE];

void main() {
    load_frame();
    uint inst = gl_WorkGroupID.x;
    uint lid = gl_LocalInvocationID.x;
    uint g = 0;
    while (g + 1 < frame.p.num_groups && inst >= groups.v[g + 1].instance_first) g++;
    uint rows = groups.v[g].rows;
    uint first = groups.v[g].splat_first - frame.p.num_background + (inst - groups.v[g].instance_first) * rows;
    for (uint c = 0; c < XFORM_GRAD_TERMS; c++) {
        float sum = 0.0;
        for (uint j = lid; j < rows; j += WG_SIZE) sum += terms.v[(first + j) * XFORM_GRAD_TERMS + c];
        partial[lid] = sum;
        barrier();
        for (uint w = WG_SIZE / 2; w > 0; w /= 2) {
            if (lid < w) partial[lid] += partial[lid + w];
            barrier();
        }
        if (lid == 0) v_xforms.v[inst * XFORM_GRAD_TERMS + c] = partial[0];
        barrier();
    }
}
