#version 450
// Loss pass 1: horizontal Gaussian filter of the SSIM moments x, y, x^2, y^2, xy per channel
// (x = render, y = ground truth), one invocation per pixel.
#include "common.glsl"
#include "ssim.glsl"
layout(local_size_x = WG_SIZE) in;
layout(push_constant) uniform Push { LossArgs a; } push;
layout(std430, binding = 0) readonly buffer ImageBuf { vec4 v[]; } image;
layout(std430, binding = 1) readonly buffer TargetBuf { vec4 v[]; } target;
layout(std430, binding = 2) writeonly buffer MomentsBuf { float v[]; } moments;

void main() {
    uint w = push.a.width, h = push.a.height, n = w * h;
    uint pix = gl_GlobalInvocationID.x;
    if (pix >= n) return;
    int px = int(pix % w);
    uint row = pix - uint(px);
    float wt[2 * SSIM_RADIUS + 1];
    ssim_weights(wt);
    vec3 m[SSIM_MOMENTS];
    for (int q = 0; q < SSIM_MOMENTS; q++) m[q] = vec3(0.0);
    for (int k = -SSIM_RADIUS; k <= SSIM_RADIUS; k++) {
        int xx = px + k;
        if (xx < 0 || xx >= int(w)) continue;
        vec3 x = image.v[row + uint(xx)].rgb;
        vec3 y = target.v[row + uint(xx)].rgb;
        float g = wt[k + SSIM_RADIUS];
        m[0] += g * x;
        m[1] += g * y;
        m[2] += g * x * x;
        m[3] += g * y * y;
        m[4] += g * x * y;
    }
    for (uint q = 0; q < SSIM_MOMENTS; q++) {
        for (uint c = 0; c < 3; c++) moments.v[(q * 3 + c) * n + pix] = m[q][c];
    }
}
