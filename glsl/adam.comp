#version 450
// One Adam step over a parameter buffer, exactly torch.optim.Adam's (non-fused) update:
//   m = m + (1 - beta1)(g - m);  v = beta2 v + (1 - beta2) g^2
//   param -= lr / (1 - beta1^t) * m / (sqrt(v) / sqrt(1 - beta2^t) + eps)
// with lr_head for the first `head` of every `stride` parameters and lr_tail for the rest, over
// the `count` parameters from `first` on. One invocation per row of `stride` parameters (no
// integer modulo per element). adam_vec4.comp is the same step four parameters at a time; this
// kernel takes the rows that are not whole vec4s and the last few parameters of a buffer.
#include "common.glsl"
layout(local_size_x = WG_SIZE) in;
layout(push_constant) uniform Push { AdamArgs a; } push;
layout(std430, binding = 0) buffer ParamsBuf { float v[]; } params;
layout(std430, binding = 1) readonly buffer GradsBuf { float v[]; } grads;
layout(std430, binding = 2) buffer ExpAvgBuf { float v[]; } exp_avg;
layout(std430, binding = 3) buffer ExpAvgSqBuf { float v[]; } exp_avg_sq;

void main() {
    uint rows = push.a.count / push.a.stride;
    for (uint g = gl_GlobalInvocationID.x; g < rows; g += gl_NumWorkGroups.x * WG_SIZE) {
        for (uint k = 0; k < push.a.stride; k++) {
            uint i = push.a.first + g * push.a.stride + k;
            float grad = grads.v[i];
            float m = exp_avg.v[i];
            m += (grad - m) * (1.0 - push.a.beta1);
            float v = push.a.beta2 * exp_avg_sq.v[i] + (1.0 - push.a.beta2) * grad * grad;
            exp_avg.v[i] = m;
            exp_avg_sq.v[i] = v;
            float lr = k < push.a.head ? push.a.lr_head : push.a.lr_tail;
            params.v[i] -= lr * push.a.inv_bias1 * m / (sqrt(v) * push.a.inv_sqrt_bias2 + push.a.eps);
        }
    }
}
