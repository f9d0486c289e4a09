#version 450
// Per-frame instance selection (rendering only; training keeps every pair), one invocation per
// instance: whole-instance frustum culling and the template level of detail.
// The instance's bounding sphere is its group's template-space sphere (the Gaussians' 3-sigma
// extents) placed by the transform, its radius grown by the instance's largest |dp| and by
// margin_px pixels at its depth (the 2D low-pass filter's spill). An instance wholly behind the
// near plane or outside one of the four side planes gets no splats. A visible one uses the
// coarsest level l <= max_level that keeps at least splats_per_pixel Gaussians per pixel of its
// projected bounding disc (pi (fx r / z)^2, at most the image); an instance the near plane cuts
// uses level 0. Writes inst_count (its splats this frame: the level's Gaussians, or 0) and
// inst_level. CPU twin: lod::select_instance.
#include "common.glsl"
layout(local_size_x = WG_SIZE) in;
layout(push_constant) uniform Push { SelectArgs a; } push;
#define FRAME_BINDING 0
#include "frame.glsl"
layout(std430, binding = 1) readonly buffer GroupsBuf { GroupInfo v[]; } groups;
layout(std430, binding = 2) readonly buffer XformsBuf { InstanceXform v[]; } xforms;
layout(std430, binding = 3) writeonly buffer InstCountBuf { uint v[]; } inst_count;
layout(std430, binding = 4) writeonly buffer InstLevelBuf { uint v[]; } inst_level;

void main() {
    load_frame();
    for (uint k = gl_GlobalInvocationID.x; k < frame.p.num_instances; k += gl_NumWorkGroups.x * WG_SIZE) {
        uint g = 0;
        while (g + 1 < frame.p.num_groups && k >= groups.v[g + 1].instance_first) g++;
        GroupInfo gi = groups.v[g];
        InstanceXform x = xforms.v[k];
        vec3 centre = (frame.p.viewmat * (x.transform * vec4(gi.bound.xyz, 1.0))).xyz;
        float fx = frame.p.intrinsics.x, fy = frame.p.intrinsics.y;
        float cx = frame.p.intrinsics.z, cy = frame.p.intrinsics.w;
        float r = x.scale.x * gi.bound.w + x.scale.z + push.a.margin_px * max(centre.z, 0.0) / min(fx, fy);
        // Side planes through the camera centre and the image edges, outward unit normals.
        float right = float(frame.p.width) - cx, bottom = float(frame.p.height) - cy;
        bool outside = centre.z + r <= frame.p.near_plane
            || dot(vec3(fx, 0.0, -right), centre) > r * length(vec3(fx, 0.0, right))
            || dot(vec3(-fx, 0.0, -cx), centre) > r * length(vec3(fx, 0.0, cx))
            || dot(vec3(0.0, fy, -bottom), centre) > r * length(vec3(0.0, fy, bottom))
            || dot(vec3(0.0, -fy, -cy), centre) > r * length(vec3(0.0, fy, cy));
        uint level = 0;
        if (!outside && centre.z - r > frame.p.near_plane) {
            float rp = min(fx, fy) * r / centre.z;
            float area = min(3.14159265 * rp * rp, float(frame.p.width) * float(frame.p.height));
            uint top = min(push.a.max_level, gi.levels - 1);
            for (uint l = top; l > 0; l--) {
                if (float(gi.level_rows[l]) >= push.a.splats_per_pixel * area) {
                    level = l;
                    break;
                }
            }
        }
        inst_count.v[k] = outside ? 0 : gi.level_rows[level];
        inst_level.v[k] = level;
    }
}
