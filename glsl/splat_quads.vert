#version 450
// The hardware-rasterized forward path (src/render/raster/quads.rs): one instance per visible
// splat (draw_args.comp), in the depth sort's front-to-back order (instance i draws
// depth_ids[i]), each a quad (QUAD_VERTICES-vertex triangle strip) that the fixed-function
// rasterizer shades pixel by pixel (splat_quads.frag) and blends front to back.
// The quad is the splat's cut-off ellipse q(d) = a dx^2 + 2 b dx dy + c dy^2 <= 2 ln(255 o)
// (conic (a, b, c), opacity o; alpha = o exp(-q/2) >= 1/255, blend.comp's cut) boxed along its
// own axes, the conic's eigenvectors: half-lengths sqrt(2 ln(255 o) / lambda), 0.1 % + 0.01 px
// wider so that no pixel centre the compute path blends is left out. Pixel coordinates have
// pixel (x, y)'s centre at (x + 0.5, y + 0.5), as gl_FragCoord and blend.comp.
#include "common.glsl"
#define FRAME_BINDING 0
#include "frame.glsl"
layout(std430, binding = 1) readonly buffer DepthIdsBuf { uint v[]; } depth_ids;
layout(std430, binding = 2) readonly buffer XysBuf { vec2 v[]; } xys;
layout(std430, binding = 3) readonly buffer ConicsBuf { vec4 v[]; } conics;
layout(std430, binding = 4) readonly buffer ColorsBuf { vec4 v[]; } colours;
layout(location = 0) flat out vec2 v_xy;
layout(location = 1) flat out vec4 v_conic;
layout(location = 2) flat out vec3 v_rgb;

void main() {
    load_frame();
    uint g = depth_ids.v[gl_InstanceIndex];
    // Strip corners 0..3 = (-,-), (+,-), (-,+), (+,+).
    uint corner = uint(gl_VertexIndex);
    vec2 xy = xys.v[g];
    vec4 co = conics.v[g];
    float a = co.x, b = co.y, c = co.z;
    float cut = max(2.0 * log(255.0 * co.w), 0.0);
    float mid = 0.5 * (a + c);
    float rad = sqrt(max(0.25 * (a - c) * (a - c) + b * b, 0.0));
    float l_big = mid + rad;
    float l_small = max(mid - rad, 1e-30);
    // An eigenvector of l_big: (l_big - c, b) or (b, l_big - a), whichever is longer.
    vec2 e1 = a >= c ? vec2(l_big - c, b) : vec2(b, l_big - a);
    float len = length(e1);
    e1 = len > 1e-30 ? e1 / len : vec2(1.0, 0.0);
    vec2 e2 = vec2(-e1.y, e1.x);
    vec2 half_len = sqrt(cut / vec2(max(l_big, 1e-30), l_small)) * 1.001 + 0.01;
    vec2 s = vec2((corner & 1u) != 0u ? 1.0 : -1.0, (corner & 2u) != 0u ? 1.0 : -1.0);
    vec2 pos = xy + s.x * half_len.x * e1 + s.y * half_len.y * e2;
    vec2 size = vec2(frame.p.width, frame.p.height);
    gl_Position = vec4(pos / size * 2.0 - 1.0, 0.0, 1.0);
    v_xy = xy;
    v_conic = co;
    v_rgb = colours.v[g].rgb;
}
