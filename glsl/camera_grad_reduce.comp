#version 450
// Camera gradients of a plain scene's frame: one workgroup sums the CAMERA_GRAD_TERMS terms that
// each workgroup of preprocess_backward's visible-rows dispatch wrote (one per WG_SIZE visible
// splats, at most MAX_GROUPS, as dispatch_args sizes it), per-thread partial sums then a
// shared-memory tree: no atomics, a fixed order (deterministic).
#include "common.glsl"
layout(local_size_x = WG_SIZE) in;
#define FRAME_BINDING 0
#include "frame.glsl"
layout(std430, binding = 1) readonly buffer TermsBuf { float v[]; } terms;
layout(std430, binding = 2) writeonly buffer GradCameraBuf { float v[]; } v_camera;

shared float partial[CAMERA_GRAD_TERMS][WG_SIZE];

void main() {
    load_frame();
    uint lid = gl_LocalInvocationID.x;
    float sum[CAMERA_GRAD_TERMS];
    for (uint c = 0; c < CAMERA_GRAD_TERMS; c++) sum[c] = 0.0;
    uint groups = min((frame.p.num_visible + WG_SIZE - 1) / WG_SIZE, MAX_GROUPS);
    for (uint j = lid; j < groups; j += WG_SIZE) {
        for (uint c = 0; c < CAMERA_GRAD_TERMS; c++) sum[c] += terms.v[j * CAMERA_GRAD_TERMS + c];
    }
    for (uint c = 0; c < CAMERA_GRAD_TERMS; c++) partial[c][lid] = sum[c];
    barrier();
    for (uint w = WG_SIZE / 2; w > 0; w /= 2) {
        if (lid < w) {
            for (uint c = 0; c < CAMERA_GRAD_TERMS; c++) partial[c][lid] += partial[c][lid + w];
        }
        barrier();
    }
    if (lid < CAMERA_GRAD_TERMS) v_camera.v[lid] = partial[lid][0];
}
