#version 450
// One Adam step over a parameter buffer, exactly torch.optim.Adam's (non-fused) update:
//   m = m + (1 - beta1)(g - m);  v = beta2 v + (1 - beta2) g^2
//   param -= lr / (1 - beta1^t) * m / (sqrt(v) / sqrt(1 - beta2^t) + eps)
// with lr_head for the first `head` of every `stride` parameters and lr_tail for the rest.
#include "common.glsl"
layout(local_size_x = WG_SIZE) in;
layout(push_constant) uniform Push { AdamArgs a; } push;
layout(std430, binding = 0) buffer ParamsBuf { float v[]; } params;
layout(std430, binding = 1) readonly buffer GradsBuf { float v[]; } grads;
layout(std430, binding = 2) buffer ExpAvgBuf { float v[]; } exp_avg;
layout(std430, binding = 3) buffer ExpAvgSqBuf { float v[]; } exp_avg_sq;

void main() {
    for (uint i = gl_GlobalInvocationID.x; i < push.a.count; i += gl_NumWorkGroups.x * WG_SIZE) {
        float g = grads.v[i];
        float m = exp_avg.v[i];
        m += (g - m) * (1.0 - push.a.beta1);
        float v = push.a.beta2 * exp_avg_sq.v[i] + (1.0 - push.a.beta2) * g * g;
        exp_avg.v[i] = m;
        exp_avg_sq.v[i] = v;
        float lr = i % push.a.stride < push.a.head ? push.a.lr_head : push.a.lr_tail;
        params.v[i] -= lr * push.a.inv_bias1 * m / (sqrt(v) * push.a.inv_sqrt_bias2 + push.a.eps);
    }
}
