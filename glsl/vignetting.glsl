// The lens's vignetting (AppearanceArgs): r^2 at pixel i of an image `width` wide, the
// normalised image coordinates of the pixel's centre, pinhole = (cx, cy, 1 / fx, 1 / fy); and the
// falloff v = 1 + k1 r^2 + k2 r^4, k = (k1, k2). CPU twin: render::appearance::radius2, falloff.
float vignetting_radius2(uint i, uint width, vec4 pinhole) {
    vec2 px = vec2(float(i % width), float(i / width)) + 0.5;
    vec2 n = (px - pinhole.xy) * pinhole.zw;
    return dot(n, n);
}

float vignetting_falloff(float r2, vec2 k) {
    return 1.0 + r2 * (k.x + r2 * k.y);
}
