#version 450
// The background under the splats: with the splats' blend state, rgb += T * background; the
// pipeline writes rgb only, so the alpha channel keeps the final T (as blend.comp's out_image).
#include "common.glsl"
#define FRAME_BINDING 0
#include "frame.glsl"
layout(location = 0) out vec4 out_colour;

void main() {
    load_frame();
    out_colour = vec4(frame.p.background.rgb, 1.0);
}
