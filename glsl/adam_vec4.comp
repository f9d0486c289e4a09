#version 450
// adam.comp's step four parameters at a time (on lavapipe every buffer access has a per-lane
// cost, so a vec4 access costs about what a float access does): `count` vec4s in rows of
// `stride` vec4s, lr_head for the first `head` parameters (not vec4s) of every row.
#include "common.glsl"
layout(local_size_x = WG_SIZE) in;
layout(push_constant) uniform Push { AdamArgs a; } push;
layout(std430, binding = 0) buffer ParamsBuf { vec4 v[]; } params;
layout(std430, binding = 1) readonly buffer GradsBuf { vec4 v[]; } grads;
layout(std430, binding = 2) buffer ExpAvgBuf { vec4 v[]; } exp_avg;
layout(std430, binding = 3) buffer ExpAvgSqBuf { vec4 v[]; } exp_avg_sq;

void main() {
    uint rows = push.a.count / push.a.stride;
    for (uint g = gl_GlobalInvocationID.x; g < rows; g += gl_NumWorkGroups.x * WG_SIZE) {
        for (uint q = 0; q < push.a.stride; q++) {
            uint i = g * push.a.stride + q;
            vec4 grad = grads.v[i];
            vec4 m = exp_avg.v[i];
            m += (grad - m) * (1.0 - push.a.beta1);
            vec4 v = push.a.beta2 * exp_avg_sq.v[i] + (1.0 - push.a.beta2) * grad * grad;
            exp_avg.v[i] = m;
            exp_avg_sq.v[i] = v;
            bvec4 head = lessThan(uvec4(4 * q) + uvec4(0, 1, 2, 3), uvec4(push.a.head));
            vec4 lr = mix(vec4(push.a.lr_tail), vec4(push.a.lr_head), head);
            params.v[i] -= lr * push.a.inv_bias1 * m / (sqrt(v) * push.a.inv_sqrt_bias2 + push.a.eps);
        }
    }
}
