#version 450
// Backward of appearance.comp. Given v_adjusted = dL/d out per pixel:
//   v_image.rgb = M^T v_adjusted.rgb (alpha 0),
//   grads[4c + j] += sum over pixels of v_adjusted[c] * rgb[j] (j < 3) and v_adjusted[c] (j = 3),
// each invocation summing its run of APPEARANCE_RUN pixels, then its subgroup, then one atomic
// add per subgroup. CPU twin: render::appearance::backward.
#extension GL_KHR_shader_subgroup_basic : require
#extension GL_KHR_shader_subgroup_arithmetic : require
#include "common.glsl"
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
    for (uint i = first; i < last; i++) {
        vec3 v = v_adjusted.v[i].rgb;
        vec4 x = vec4(image.v[i].rgb, 1.0);
        v_image.v[i] = vec4(mt * v, 0.0);
        g0 += v.r * x;
        g1 += v.g * x;
        g2 += v.b * x;
    }
    g0 = subgroupAdd(g0);
    g1 = subgroupAdd(g1);
    g2 = subgroupAdd(g2);
    if (subgroupElect()) {
        for (uint j = 0; j < 4; j++) {
            ATOMIC_ADD_F(grads.v, j, g0[j]);
            ATOMIC_ADD_F(grads.v, 4 + j, g1[j]);
            ATOMIC_ADD_F(grads.v, 8 + j, g2[j]);
        }
    }
}
