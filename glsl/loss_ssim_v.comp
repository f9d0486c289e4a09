#version 450
// Loss pass 2, one invocation per pixel: vertical Gaussian filter of the moments, the SSIM map
//   S = (2 mx my + C1)(2 sxy + C2) / ((mx^2 + my^2 + C1)(sx^2 + sy^2 + C2))
// with sx^2 = E[x^2] - mx^2 and sxy = E[xy] - mx my, the loss sums (|x - y| and S, subgroup
// reduced, then added to `loss`) and the SSIM cotangents scaled by -lambda / count:
//   dS/dmx (total), dS/dE[x^2] = -S / B2, dS/dE[xy] = 2 A1 / (B1 B2).
// The gradient of the mean SSIM with respect to x(q) is then the same filter applied to these
// maps (loss_cotangents_h, loss_grad_v).
#include "common.glsl"
#include "ssim.glsl"
#include "atomic_add.glsl"
#extension GL_KHR_shader_subgroup_basic : require
#extension GL_KHR_shader_subgroup_arithmetic : require
layout(local_size_x = WG_SIZE) in;
layout(push_constant) uniform Push { LossArgs a; } push;
layout(std430, binding = 0) readonly buffer ImageBuf { vec4 v[]; } image;
layout(std430, binding = 1) readonly buffer TargetBuf { vec4 v[]; } target;
layout(std430, binding = 2) readonly buffer MomentsBuf { float v[]; } moments;
layout(std430, binding = 3) writeonly buffer CotangentsBuf { float v[]; } cotangents;
layout(std430, binding = 4) buffer LossBuf { GRAD_T v[]; } loss;

void main() {
    uint w = push.a.width, h = push.a.height, n = w * h;
    uint pix = gl_GlobalInvocationID.x;
    bool inside = pix < n;
    float l1 = 0.0, ssim = 0.0;
    if (inside) {
        int py = int(pix / w);
        uint px = pix - uint(py) * w;
        float wt[2 * SSIM_RADIUS + 1];
        ssim_weights(wt);
        vec3 m[SSIM_MOMENTS];
        for (int q = 0; q < SSIM_MOMENTS; q++) m[q] = vec3(0.0);
        for (int k = -SSIM_RADIUS; k <= SSIM_RADIUS; k++) {
            int yy = py + k;
            if (yy < 0 || yy >= int(h)) continue;
            uint src = uint(yy) * w + px;
            float g = wt[k + SSIM_RADIUS];
            for (uint q = 0; q < SSIM_MOMENTS; q++) {
                m[q] += g * vec3(moments.v[(q * 3) * n + src], moments.v[(q * 3 + 1) * n + src],
                                 moments.v[(q * 3 + 2) * n + src]);
            }
        }
        vec3 mx = m[0], my = m[1];
        vec3 sxx = m[2] - mx * mx, syy = m[3] - my * my, sxy = m[4] - mx * my;
        vec3 A1 = 2.0 * mx * my + SSIM_C1, A2 = 2.0 * sxy + SSIM_C2;
        vec3 B1 = mx * mx + my * my + SSIM_C1, B2 = sxx + syy + SSIM_C2;
        vec3 S = A1 * A2 / (B1 * B2);
        vec3 d_exx = -S / B2;
        vec3 d_exy = 2.0 * A1 / (B1 * B2);
        vec3 d_mx = 2.0 * my * A2 / (B1 * B2) - S * 2.0 * mx / B1 - 2.0 * mx * d_exx - my * d_exy;
        float scale = -push.a.ssim_weight * push.a.inv_count;
        for (uint c = 0; c < 3; c++) {
            cotangents.v[c * n + pix] = scale * d_mx[c];
            cotangents.v[(3 + c) * n + pix] = scale * d_exx[c];
            cotangents.v[(6 + c) * n + pix] = scale * d_exy[c];
        }
        vec3 d = abs(image.v[pix].rgb - target.v[pix].rgb);
        l1 = d.x + d.y + d.z;
        ssim = S.x + S.y + S.z;
    }
    l1 = subgroupAdd(l1);
    ssim = subgroupAdd(ssim);
    if (subgroupElect()) {
        ATOMIC_ADD_F(loss.v, LOSS_L1, l1);
        ATOMIC_ADD_F(loss.v, LOSS_SSIM, ssim);
    }
}
