#version 450
// The per-photo colour transform and the lens's vignetting of a rendered image
// (AppearanceArgs): out.rgb = v(r) (M rgb + b), v = 1 + k1 r^2 + k2 r^4, alpha copied. One
// invocation per run of APPEARANCE_RUN pixels. CPU twin: render::appearance::apply_photo.
#include "common.glsl"
#include "vignetting.glsl"
layout(local_size_x = WG_SIZE) in;
layout(push_constant) uniform Push { AppearanceArgs a; } push;
layout(std430, binding = 0) readonly buffer ImageBuf { vec4 v[]; } image;
layout(std430, binding = 1) writeonly buffer AdjustedBuf { vec4 v[]; } adjusted;

void main() {
    uint first = gl_GlobalInvocationID.x * APPEARANCE_RUN;
    uint last = min(first + APPEARANCE_RUN, push.a.pixels);
    for (uint i = first; i < last; i++) {
        vec4 p = image.v[i];
        vec4 x = vec4(p.rgb, 1.0);
        float r2 = vignetting_radius2(i, push.a.width, push.a.pinhole);
        float v = vignetting_falloff(r2, push.a.vignetting.xy);
        adjusted.v[i] = vec4(v * vec3(dot(push.a.row0, x), dot(push.a.row1, x), dot(push.a.row2, x)), p.a);
    }
}
