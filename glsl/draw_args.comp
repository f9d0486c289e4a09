#version 450
// The draw path's VkDrawIndirectCommand from the GPU-written visible count: one instance of
// QUAD_VERTICES vertices (a triangle strip) per visible splat (splat_quads.vert).
#include "common.glsl"
layout(local_size_x = 1) in;
layout(std430, binding = 0) readonly buffer CountsBuf { uint v[]; } counts;
layout(std430, binding = 1) writeonly buffer DrawArgsBuf { uint v[]; } draw_args;

void main() {
    draw_args.v[0] = QUAD_VERTICES;
    draw_args.v[1] = counts.v[COUNT_VISIBLE];
    draw_args.v[2] = 0;
    draw_args.v[3] = 0;
}
