#version 450
// Loss pass 4, one invocation per run of LOSS_RUN pixels down a column: vertical filter of the cotangents and the image gradient
//   dL/dx = F(d_mx) + 2 x F(d_exx) + y F(d_exy) + (1 - lambda) sign(x - y) / count
// (F = the zero-padded Gaussian filter, its own adjoint). Alpha of v_image is 0.
#include "common.glsl"
#include "ssim.glsl"
layout(local_size_x = WG_SIZE) in;
layout(push_constant) uniform Push { LossArgs a; } push;
layout(std430, binding = 0) readonly buffer ImageBuf { vec4 v[]; } image;
layout(std430, binding = 1) readonly buffer TargetBuf { vec4 v[]; } target;
layout(std430, binding = 2) readonly buffer FilteredBuf { float v[]; } filtered;
layout(std430, binding = 3) writeonly buffer VImageBuf { vec4 v[]; } v_image;

const int SPAN = LOSS_RUN + 2 * SSIM_RADIUS;

void main() {
    uint w = push.a.width, h = push.a.height, n = w * h;
    uint runs_y = (h + LOSS_RUN - 1) / LOSS_RUN;
    uint run = gl_GlobalInvocationID.x;
    if (run >= runs_y * w) return;
    uint px = run % w;
    int y0 = int(run / w) * LOSS_RUN;
    float wt[2 * SSIM_RADIUS + 1];
    ssim_weights(wt);
    float m[LOSS_RUN][SSIM_COTANGENTS * 3];
    for (uint q = 0; q < SSIM_COTANGENTS * 3; q++) {
        float vals[SPAN];
        for (int k = 0; k < SPAN; k++) {
            int yy = y0 - SSIM_RADIUS + k;
            vals[k] = yy >= 0 && yy < int(h) ? filtered.v[q * n + uint(yy) * w + px] : 0.0;
        }
        for (int o = 0; o < LOSS_RUN; o++) {
            float acc = 0.0;
            for (int k = 0; k <= 2 * SSIM_RADIUS; k++) acc += wt[k] * vals[o + k];
            m[o][q] = acc;
        }
    }
    for (int o = 0; o < LOSS_RUN && y0 + o < int(h); o++) {
        uint pix = uint(y0 + o) * w + px;
        vec3 f0 = vec3(m[o][0], m[o][1], m[o][2]);
        vec3 f1 = vec3(m[o][3], m[o][4], m[o][5]);
        vec3 f2 = vec3(m[o][6], m[o][7], m[o][8]);
        vec3 x = image.v[pix].rgb, y = target.v[pix].rgb;
        vec3 g = f0 + 2.0 * x * f1 + y * f2 + (1.0 - push.a.ssim_weight) * push.a.inv_count * sign(x - y);
        v_image.v[pix] = vec4(g, 0.0);
    }
}
