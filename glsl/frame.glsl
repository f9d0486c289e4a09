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
    frame.p.viewmat = mat4(uintBitsToFloat(t[0]), uintBitsToFloat(t[1]), uintBitsToFloat(t[2]), uintBitsToFloat(t[3]));
    frame.p.intrinsics = uintBitsToFloat(t[4]);
    frame.p.campos = uintBitsToFloat(t[5]);
    frame.p.background = uintBitsToFloat(t[6]);
    frame.p.width = t[7].x;
    frame.p.height = t[7].y;
    frame.p.tiles_x = t[7].z;
    frame.p.tiles_y = t[7].w;
    frame.p.num_gaussians = t[8].x;
    frame.p.sh_degree = t[8].y;
    frame.p.sh_coeffs = t[8].z;
    frame.p.isect_capacity = t[8].w;
    frame.p.near_plane = uintBitsToFloat(t[9].x);
    frame.p.far_plane = uintBitsToFloat(t[9].y);
    frame.p.num_background = t[9].z;
    frame.p.num_groups = t[9].w;
    frame.p.num_rows = t[10].x;
    frame.p.xform_grads = t[10].y;
    frame.p.select = t[10].z;
    frame.p.num_instances = t[10].w;
    frame.p.offset_codes = t[11].x;
    frame.p.num_visible = t[11].y;
    frame.p._pad1 = t[11].z;
    frame.p._pad2 = t[11].w;
}
#endif
