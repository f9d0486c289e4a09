#version 450
// Loss pass 3: horizontal Gaussian filter of the SSIM cotangent maps. One invocation per run of
// LOSS_RUN pixels of a row.
#include "common.glsl"
#include "ssim.glsl"
layout(local_size_x = WG_SIZE) in;
layout(push_constant) uniform Push { LossArgs a; } push;
layout(std430, binding = 0) readonly buffer CotangentsBuf { float v[]; } cotangents;
layout(std430, binding = 1) writeonly buffer FilteredBuf { float v[]; } filtered;

const int SPAN = LOSS_RUN + 2 * SSIM_RADIUS;

void main() {
    uint w = push.a.width, h = push.a.height, n = w * h;
    uint runs_x = (w + LOSS_RUN - 1) / LOSS_RUN;
    uint run = gl_GlobalInvocationID.x;
    if (run >= runs_x * h) return;
    uint row = (run / runs_x) * w;
    int x0 = int(run % runs_x) * LOSS_RUN;
    float wt[2 * SSIM_RADIUS + 1];
    ssim_weights(wt);
    for (uint q = 0; q < SSIM_COTANGENTS * 3; q++) {
        float vals[SPAN];
        for (int k = 0; k < SPAN; k++) {
            int xx = x0 - SSIM_RADIUS + k;
            vals[k] = xx >= 0 && xx < int(w) ? cotangents.v[q * n + row + uint(xx)] : 0.0;
        }
        for (int o = 0; o < LOSS_RUN && x0 + o < int(w); o++) {
            float acc = 0.0;
            for (int k = 0; k <= 2 * SSIM_RADIUS; k++) acc += wt[k] * vals[o + k];
            filtered.v[q * n + row + uint(x0 + o)] = acc;
        }
    }
}
