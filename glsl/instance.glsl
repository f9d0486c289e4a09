// Instancing (InstGS, paper Eq. 6): splat i is either background Gaussian i or the pair
// (template Gaussian j, instance k) of a group, expanded on the fly and never stored:
//   mean = s R mean_t + t + dp,  log-scales = log-scales_t + ln s,  quat = q_T * q_t,
//   opacity logit = logit_t + do,  SH DC = dc_t + dc,  higher SH evaluated in template space
//   at the direction R^T d (view-dependent colour turns with the instance).
// Offsets (frame.p.offset_storage, common.glsl) are f32 arrays; or product-quantised
// (crate::formats::pq8): per pair 16 bits in d_codes (two pairs per word, low half first), the
// low byte indexing the group's dp codebook (codebooks[group * 512 + code].xyz), the high byte
// its (d SH DC, d opacity) codebook (codebooks[group * 512 + 256 + code]); or f16: pair p's
// OFFSET_HALVES halves (dp xyz, d SH DC rgb, d opacity) are halves 7p .. 7p + 6 of d_codes (two
// per word, low half first), so they lie in the four words from 7p / 2 on, from the high half of
// the first where p is odd.
// The including kernel declares `frame` (frame.glsl) and the parameter buffers means, scales,
// quats, opacities as samplerBuffers, and defines INSTANCE_BINDING, the first of the seven bindings below.
#include "texels.glsl"
layout(std430, binding = INSTANCE_BINDING) readonly buffer GroupsBuf { GroupInfo v[]; } groups;
layout(std430, binding = INSTANCE_BINDING + 1) readonly buffer XformsBuf { InstanceXform v[]; } xforms;
layout(std430, binding = INSTANCE_BINDING + 2) readonly buffer DMeansBuf { float v[]; } d_means;
layout(std430, binding = INSTANCE_BINDING + 3) readonly buffer DSh0Buf { float v[]; } d_sh0;
layout(std430, binding = INSTANCE_BINDING + 4) readonly buffer DOpacitiesBuf { float v[]; } d_opacities;
layout(std430, binding = INSTANCE_BINDING + 5) readonly buffer DCodesBuf { uint v[]; } d_codes;
layout(std430, binding = INSTANCE_BINDING + 6) readonly buffer CodebooksBuf { vec4 v[]; } codebooks;

// Rotation matrix of a unit (w, x, y, z) quaternion.
mat3 quat_to_mat(vec4 q) {
    float w = q.x, x = q.y, y = q.z, z = q.w;
    return mat3(1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y + w * z), 2.0 * (x * z - w * y),
                2.0 * (x * y - w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z + w * x),
                2.0 * (x * z + w * y), 2.0 * (y * z - w * x), 1.0 - 2.0 * (x * x + y * y));
}

// Hamilton product a * b of (w, x, y, z) quaternions.
vec4 quat_mul(vec4 a, vec4 b) {
    return vec4(a.x * b.x - a.y * b.y - a.z * b.z - a.w * b.w, a.x * b.y + a.y * b.x + a.z * b.w - a.w * b.z,
                a.x * b.z - a.y * b.w + a.z * b.x + a.w * b.y, a.x * b.w + a.y * b.z - a.z * b.y + a.w * b.x);
}

// Where splat i comes from: its parameter row, and for an instanced splat its offset pair index,
// transform and group (NO_SLOT for a background Gaussian).
struct SplatRef {
    uint row;
    uint pair;
    uint xform;
    uint group;
};

SplatRef splat_ref(uint i) {
    if (i < frame.p.num_background) return SplatRef(i, NO_SLOT, NO_SLOT, NO_SLOT);
    uint g = 0;
    while (g + 1 < frame.p.num_groups && i >= groups.v[g + 1].splat_first) g++;
    uint local = i - groups.v[g].splat_first;
    uint rows = groups.v[g].rows;
    uint k = local / rows;
    return SplatRef(groups.v[g].row_first + local - k * rows, i - frame.p.num_background, groups.v[g].instance_first + k, g);
}

// A splat's expanded parameters (the quaternion raw, as stored, not normalised), its SH DC
// offset and the rotation that maps template directions to world directions.
struct Expanded {
    vec3 mean;
    vec3 log_scale;
    vec4 quat;
    float logit;
    vec3 dc;
    mat3 rot;
};

Expanded expand(SplatRef r) {
    uint row = r.row;
    Expanded e;
    e.mean = texel_vec3(means, 3 * row);
    e.log_scale = texel_vec3(scales, 3 * row);
    e.quat = texelFetch(quats, int(row));
    e.logit = texel_f32(opacities, row);
    e.dc = vec3(0.0);
    e.rot = mat3(1.0);
    if (r.pair != NO_SLOT) {
        InstanceXform x = xforms.v[r.xform];
        uint p = r.pair;
        vec3 dp;
        float dop;
        if (frame.p.offset_storage == OFFSETS_F16) {
            uint w = (OFFSET_HALVES * p) >> 1;
            uvec4 h = uvec4(d_codes.v[w], d_codes.v[w + 1], d_codes.v[w + 2], d_codes.v[w + 3]);
            if ((p & 1) != 0) h = uvec4((h.xyz >> 16) | (h.yzw << 16), h.w >> 16);
            vec2 a = unpackHalf2x16(h.x), b = unpackHalf2x16(h.y), c = unpackHalf2x16(h.z);
            dp = vec3(a, b.x);
            e.dc = vec3(b.y, c);
            dop = unpackHalf2x16(h.w).x;
        } else if (frame.p.offset_storage == OFFSETS_PQ8) {
            uint code = (d_codes.v[p >> 1] >> (16 * (p & 1))) & 0xFFFF;
            dp = codebooks.v[r.group * 512 + (code & 0xFF)].xyz;
            vec4 c = codebooks.v[r.group * 512 + 256 + (code >> 8)];
            e.dc = c.xyz;
            dop = c.w;
        } else {
            dp = vec3(d_means.v[3 * p], d_means.v[3 * p + 1], d_means.v[3 * p + 2]);
            e.dc = vec3(d_sh0.v[3 * p], d_sh0.v[3 * p + 1], d_sh0.v[3 * p + 2]);
            dop = d_opacities.v[p];
        }
        e.mean = (x.transform * vec4(e.mean, 1.0)).xyz + dp;
        e.log_scale += x.scale.y;
        e.quat = quat_mul(x.quat, e.quat);
        e.logit += dop;
        e.rot = quat_to_mat(x.quat);
    }
    return e;
}
