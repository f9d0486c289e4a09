// Elements of arrays read through texel-buffer views of their storage buffers (RGBA32F
// `samplerBuffer`, RGBA32UI `usamplerBuffer`; the buffers are whole texels underneath): lavapipe
// fetches a texel with one vector gather, where a storage-buffer load is a loop over the lanes.
#ifndef INSTGS_TEXELS_GLSL
#define INSTGS_TEXELS_GLSL
// Element i of a uint array (four per texel).
uint texel_u32(usamplerBuffer b, uint i) {
    return texelFetch(b, int(i / 4))[i & 3];
}

// Element i of a float array (four per texel).
float texel_f32(samplerBuffer b, uint i) {
    return texelFetch(b, int(i / 4))[i & 3];
}

// Element i of a vec2 array (two per texel).
vec2 texel_vec2(samplerBuffer b, uint i) {
    vec4 two = texelFetch(b, int(i / 2));
    return (i & 1) == 0 ? two.xy : two.zw;
}

// Element i of a uvec2 array (two per texel).
uvec2 texel_uvec2(usamplerBuffer b, uint i) {
    uvec4 two = texelFetch(b, int(i / 2));
    return (i & 1) == 0 ? two.xy : two.zw;
}

// Floats f, f + 1, f + 2 of a float array (the second texel clamped to the last).
vec3 texel_vec3(samplerBuffer b, uint f) {
    vec4 lo = texelFetch(b, int(f / 4));
    vec4 hi = texelFetch(b, min(int(f / 4) + 1, textureSize(b) - 1));
    uint o = f & 3;
    return o == 0 ? lo.xyz : o == 1 ? lo.yzw : o == 2 ? vec3(lo.zw, hi.x) : vec3(lo.w, hi.xy);
}
#endif
