// The frame parameters (FrameParams, common.glsl) for kernels: the small frame buffer bound as
// RGBA32UI texels (`frame_texels`) and read once per invocation by load_frame() into the private
// `frame.p`, which the kernel then reads as if it were the buffer. lavapipe fetches a texel with
// one vector gather, where every component read from a storage buffer is a loop over the lanes
// (BENCHMARKS.md, "Texel fetches on lavapipe"); kernels read the frame's fields many times per
// invocation. The including kernel defines FRAME_BINDING.
#ifndef INSTGS_FRAME_GLSL
#define INSTGS_FRAME_GLSL
layout(binding = FRAME_BINDING) uniform usamplerBuffer frame_texels;
struct FrameBlock {
    FrameParams p;
};
FrameBlock frame;

void load_frame() {
    uvec4 t[12];
    for (int k = 0; k < 12; k++) t[k] = texelFetch(frame_texels, k);
    vec4 f[7];
    for (int k = 0; k < 7; k++) f[k] = uintBitsToFloat(t[k]);
    // The fields in declaration order: viewmat, intrinsics, campos, background, then from
    // texel 7 on the scalars (near_plane, far_plane and tile_cost_weight floats, the rest uints).
    frame.p = FrameParams(mat4(f[0], f[1], f[2], f[3]), f[4], f[5], f[6],
                          t[7].x, t[7].y, t[7].z, t[7].w, t[8].x, t[8].y, t[8].z, t[8].w,
                          uintBitsToFloat(t[9].x), uintBitsToFloat(t[9].y), t[9].z, t[9].w,
                          t[10].x, t[10].y, t[10].z, t[10].w, t[11].x, t[11].y, uintBitsToFloat(t[11].z), t[11].w);
}
#endif
