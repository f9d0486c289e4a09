#version 450
// Loss pass 1: horizontal Gaussian filter of the SSIM moments x, y, x^2, y^2, xy per channel
// (x = render, y = ground truth). One invocation per run of LOSS_RUN pixels of a row.
#include "common.glsl"
#include "ssim.glsl"
layout(local_size_x = WG_SIZE) in;
layout(push_constant) uniform Push { LossArgs a; } push;
layout(std430, binding = 0) readonly buffer ImageBuf { vec4 v[]; } image;
layout(std430, binding = 1) readonly buffer TargetBuf { vec4 v[]; } target;
layout(std430, binding = 2) writeonly buffer MomentsBuf { float v[]; } moments;

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
    vec3 xs[SPAN], ys[SPAN];
    for (int k = 0; k < SPAN; k++) {
        int xx = x0 - SSIM_RADIUS + k;
        bool inside = xx >= 0 && xx < int(w);
        xs[k] = inside ? image.v[row + uint(xx)].rgb : vec3(0.0);
        ys[k] = inside ? target.v[row + uint(xx)].rgb : vec3(0.0);
    }
    for (int o = 0; o < LOSS_RUN && x0 + o < int(w); o++) {
        vec3 m[SSIM_MOMENTS];
        for (int q = 0; q < SSIM_MOMENTS; q++) m[q] = vec3(0.0);
        for (int k = 0; k <= 2 * SSIM_RADIUS; k++) {
            vec3 x = xs[o + k], y = ys[o + k];
            float g = wt[k];
            m[0] += g * x;
            m[1] += g * y;
            m[2] += g * x * x;
            m[3] += g * y * y;
            m[4] += g * x * y;
        }
        uint pix = row + uint(x0 + o);
        for (uint q = 0; q < SSIM_MOMENTS; q++) {
            for (uint c = 0; c < 3; c++) moments.v[(q * 3 + c) * n + pix] = m[q][c];
        }
    }
}
