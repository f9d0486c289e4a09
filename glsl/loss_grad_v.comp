#version 450
// Loss pass 4: vertical filter of the cotangents and the image gradient
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

void main() {
    uint w = push.a.width, h = push.a.height, n = w * h;
    uint pix = gl_GlobalInvocationID.x;
    if (pix >= n) return;
    int py = int(pix / w);
    uint px = pix - uint(py) * w;
    float wt[2 * SSIM_RADIUS + 1];
    ssim_weights(wt);
    vec3 m[SSIM_COTANGENTS];
    for (int q = 0; q < SSIM_COTANGENTS; q++) m[q] = vec3(0.0);
    for (int k = -SSIM_RADIUS; k <= SSIM_RADIUS; k++) {
        int yy = py + k;
        if (yy < 0 || yy >= int(h)) continue;
        uint src = uint(yy) * w + px;
        float g = wt[k + SSIM_RADIUS];
        for (uint q = 0; q < SSIM_COTANGENTS; q++) {
            m[q] += g * vec3(filtered.v[(q * 3) * n + src], filtered.v[(q * 3 + 1) * n + src],
                             filtered.v[(q * 3 + 2) * n + src]);
        }
    }
    vec3 x = image.v[pix].rgb, y = target.v[pix].rgb;
    vec3 g = m[0] + 2.0 * x * m[1] + y * m[2] + (1.0 - push.a.ssim_weight) * push.a.inv_count * sign(x - y);
    v_image.v[pix] = vec4(g, 0.0);
}
