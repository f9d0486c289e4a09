#version 450
// One pixel of one splat (splat_quads.vert): alpha as blend.comp (min(0.99, o exp(-q/2)),
// nothing below 1/255 or where q < 0), written premultiplied. The pipeline blends front to back
// with the transmittance T in the attachment's alpha (cleared to 1): rgb += T * (alpha rgb),
// T *= 1 - alpha (src factors DST_ALPHA / ZERO, dst factors ONE / ONE_MINUS_SRC_ALPHA).
layout(location = 0) flat in vec2 v_xy;
layout(location = 1) flat in vec4 v_conic;
layout(location = 2) flat in vec3 v_rgb;
layout(location = 0) out vec4 out_colour;

void main() {
    vec2 d = v_xy - gl_FragCoord.xy;
    vec4 co = v_conic;
    float power = -0.5 * (co.x * d.x * d.x + co.z * d.y * d.y) - co.y * d.x * d.y;
    float alpha = min(0.99, co.w * exp(power));
    if (power > 0.0 || alpha < 1.0 / 255.0) discard;
    out_colour = vec4(v_rgb * alpha, alpha);
}
