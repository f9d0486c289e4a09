#version 450
// Backward of appearance.comp. Given v_adjusted = dL/d out per pixel, with u = M rgb + b and
// out = v(r) u:
//   v_image.rgb = v(r) M^T v_adjusted.rgb (alpha 0),
//   grads[4c + j] += sum over pixels of v(r) v_adjusted[c] * rgb[j] (j < 3) and v(r) v_adjusted[c]
//   (j = 3), grads[12] += sum of r^2 <v_adjusted, u>, grads[13] += sum of r^4 <v_adjusted, u>,
// each invocation summing its run of APPEARANCE_RUN pixels, then its subgroup, then one atomic
// add per subgroup. CPU twin: render::appearance::backward.
#extension GL_KHR_shader_subgroup_basic : require
#extension GL_KHR_shader_subgroup_arithmetic : require
#include "common.glsl"
#include "vignetting.glsl"
#include "atomic_add.glsl"
layout(local_size_x = WG_SIZE) in;
layout(push_constant) uniform Push { AppearanceArgs a; } push;
layout(std430, binding = 0) readonly buffer ImageBuf { vec4 v[]; } image;
layout(std430, binding = 1) readonly buffer VAdjustedBuf { vec4 v[]; } v_adjusted;
layout(std430, binding = 2) writeonly buffer VImageBuf { vec4 v[]; } v_image;
layout(std430, binding = 3) buffer GradsBuf { GRAD_T v[]; } grads;

void main() {
    mat3 mt = mat3(push.a.row0.xyz, push.a.row1.xyz, push.a.row2.xyz); // columns: M's rows, so M^T
    uint first = gl_GlobalInvocationID.x * APPEARANCE_RUN;
    uint last = min(first + APPEARANCE_RUN, push.a.pixels);
    vec4 g0 = vec4(0.0), g1 = vec4(0.0), g2 = vec4(0.0);
    vec2 gk = vec2(0.0);
    for (uint i = first; i < last; i++) {
        vec4 x = vec4(image.v[i].rgb, 1.0);
        float r2 = vignetting_radius2(i, push.a.width, push.a.pinhole);
        float f = vignetting_falloff(r2, push.a.vignetting.xy);
        vec3 vo = v_adjusted.v[i].rgb;
        vec3 u = vec3(dot(push.a.row0, x), dot(push.a.row1, x), dot(push.a.row2, x));
        float vu = dot(vo, u);
        gk += vec2(r2, r2 * r2) * vu;
        vec3 v = f * vo;
        v_image.v[i] = vec4(mt * v, 0.0);
        g0 += v.r * x;
        g1 += v.g * x;
        g2 += v.b * x;
    }
    g0 = subgroupAdd(g0);
    g1 = subgroupAdd(g1);
    g2 = subgroupAdd(g2);
    gk = subgroupAdd(gk);
    if (subgroupElect()) {
        for (uint j = 0; j < 4; j++) {
            ATOMIC_ADD_F(grads.v, j, g0[j]);
            ATOMIC_ADD_F(grads.v, 4 + j, g1[j]);
            ATOMIC_ADD_F(grads.v, 8 + j, g2[j]);
        }
        ATOMIC_ADD_F(grads.v, APPEARANCE_PARAMS, gk.x);
        ATOMIC_ADD_F(grads.v, APPEARANCE_PARAMS + 1, gk.y);
    }
}
