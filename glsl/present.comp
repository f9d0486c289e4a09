#version 450
// The player's last step: the rasterizer's image (RGBA f32; rgb = C + T background) packed as
// 8-bit texels for a copy into the swapchain image, with the text overlay (RGBA8, straight
// alpha, row-major overlay_width wide) blended over the top-left corner. Values are stored as
// they are, as every 3DGS renderer writes its PNGs (trained colours are display values); an
// _SRGB swapchain would encode them again on write, so they are decoded first there. Opaque.
// CPU twin: player::present_texel.
#include "common.glsl"
layout(local_size_x = WG_SIZE) in;
layout(push_constant) uniform Push { PresentArgs a; } push;
layout(std430, binding = 0) readonly buffer ImageBuf { vec4 v[]; } image;
layout(std430, binding = 1) readonly buffer OverlayBuf { uint v[]; } overlay;
layout(std430, binding = 2) writeonly buffer TexelsBuf { uint v[]; } texels;

vec3 srgb_to_linear(vec3 c) {
    return mix(c / 12.92, pow((c + 0.055) / 1.055, vec3(2.4)), greaterThan(c, vec3(0.04045)));
}

void main() {
    uint pixels = push.a.width * push.a.height;
    for (uint i = gl_GlobalInvocationID.x; i < pixels; i += gl_NumWorkGroups.x * WG_SIZE) {
        vec3 c = clamp(image.v[i].rgb, 0.0, 1.0);
        uint x = i % push.a.width, y = i / push.a.width;
        if (x < push.a.overlay_width && y < push.a.overlay_height) {
            vec4 o = unpackUnorm4x8(overlay.v[y * push.a.overlay_width + x]);
            c = mix(c, o.rgb, o.a);
        }
        if (push.a.srgb_decode != 0) c = srgb_to_linear(c);
        if (push.a.bgra != 0) c = c.bgr;
        texels.v[i] = packUnorm4x8(vec4(c, 1.0));
    }
}
