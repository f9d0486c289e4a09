#version 450
// Loss pass 2, one invocation per run of LOSS_RUN pixels down a column: vertical Gaussian filter of the moments, the SSIM map
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

const int SPAN = LOSS_RUN + 2 * SSIM_RADIUS;

void main() {
    uint w = push.a.width, h = push.a.height, n = w * h;
    uint runs_y = (h + LOSS_RUN - 1) / LOSS_RUN;
    uint run = gl_GlobalInvocationID.x;
    bool in_image = run < runs_y * w;
    uint px = run % w;
    int y0 = int(run / w) * LOSS_RUN;
    float l1 = 0.0, ssim = 0.0;
    if (in_image) {
        float wt[2 * SSIM_RADIUS + 1];
        ssim_weights(wt);
        float m[LOSS_RUN][SSIM_MOMENTS * 3];
        for (uint q = 0; q < SSIM_MOMENTS * 3; q++) {
            float vals[SPAN];
            for (int k = 0; k < SPAN; k++) {
                int yy = y0 - SSIM_RADIUS + k;
                vals[k] = yy >= 0 && yy < int(h) ? moments.v[q * n + uint(yy) * w + px] : 0.0;
            }
            for (int o = 0; o < LOSS_RUN; o++) {
                float acc = 0.0;
                for (int k = 0; k <= 2 * SSIM_RADIUS; k++) acc += wt[k] * vals[o + k];
                m[o][q] = acc;
            }
        }
        float scale = -push.a.ssim_weight * push.a.inv_count;
        for (int o = 0; o < LOSS_RUN && y0 + o < int(h); o++) {
            uint pix = uint(y0 + o) * w + px;
            vec3 mx = vec3(m[o][0], m[o][1], m[o][2]), my = vec3(m[o][3], m[o][4], m[o][5]);
            vec3 exx = vec3(m[o][6], m[o][7], m[o][8]), eyy = vec3(m[o][9], m[o][10], m[o][11]);
            vec3 exy = vec3(m[o][12], m[o][13], m[o][14]);
            vec3 sxx = exx - mx * mx, syy = eyy - my * my, sxy = exy - mx * my;
            vec3 A1 = 2.0 * mx * my + SSIM_C1, A2 = 2.0 * sxy + SSIM_C2;
            vec3 B1 = mx * mx + my * my + SSIM_C1, B2 = sxx + syy + SSIM_C2;
            vec3 S = A1 * A2 / (B1 * B2);
            vec3 d_exx = -S / B2;
            vec3 d_exy = 2.0 * A1 / (B1 * B2);
            vec3 d_mx = 2.0 * my * A2 / (B1 * B2) - S * 2.0 * mx / B1 - 2.0 * mx * d_exx - my * d_exy;
            for (uint c = 0; c < 3; c++) {
                cotangents.v[c * n + pix] = scale * d_mx[c];
                cotangents.v[(3 + c) * n + pix] = scale * d_exx[c];
                cotangents.v[(6 + c) * n + pix] = scale * d_exy[c];
            }
            vec3 d = abs(image.v[pix].rgb - target.v[pix].rgb);
            l1 += d.x + d.y + d.z;
            ssim += S.x + S.y + S.z;
        }
    }
    l1 = subgroupAdd(l1);
    ssim = subgroupAdd(ssim);
    if (subgroupElect()) {
        ATOMIC_ADD_F(loss.v, LOSS_L1, l1);
        ATOMIC_ADD_F(loss.v, LOSS_SSIM, ssim);
    }
}
