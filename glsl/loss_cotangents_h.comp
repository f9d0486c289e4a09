#version 450
// Loss pass 3: horizontal Gaussian filter of the SSIM cotangent maps, one invocation per pixel.
#include "common.glsl"
#include "ssim.glsl"
layout(local_size_x = WG_SIZE) in;
layout(push_constant) uniform Push { LossArgs a; } push;
layout(std430, binding = 0) readonly buffer CotangentsBuf { float v[]; } cotangents;
layout(std430, binding = 1) writeonly buffer FilteredBuf { float v[]; } filtered;

void main() {
    uint w = push.a.width, h = push.a.height, n = w * h;
    uint pix = gl_GlobalInvocationID.x;
    if (pix >= n) return;
    int px = int(pix % w);
    uint row = pix - uint(px);
    float wt[2 * SSIM_RADIUS + 1];
    ssim_weights(wt);
    float m[SSIM_COTANGENTS * 3];
    for (int q = 0; q < SSIM_COTANGENTS * 3; q++) m[q] = 0.0;
    for (int k = -SSIM_RADIUS; k <= SSIM_RADIUS; k++) {
        int xx = px + k;
        if (xx < 0 || xx >= int(w)) continue;
        float g = wt[k + SSIM_RADIUS];
        for (uint q = 0; q < SSIM_COTANGENTS * 3; q++) m[q] += g * cotangents.v[q * n + row + uint(xx)];
    }
    for (uint q = 0; q < SSIM_COTANGENTS * 3; q++) filtered.v[q * n + pix] = m[q];
}
