#version 450
// Gradient-driven segmentation (InstGS Eq. 3), one invocation per splat: adds one mask's
// per-splat score to scores[slot * count + i] with a weight (1 for an instance mask M, -alpha for
// the pass over all pixels; GSeg(1 - M) = GSeg(1) - GSeg(M) since the score is linear in the
// mask). The score is the colour gradient of L = sum over the mask's pixels of mean(rgb), read
// from blend_backward's v_colours: the sum of the splat's blending weights T alpha over the mask.
// The colour channels are independent in that gradient, so one backward pass carries up to three
// masks, one per channel (channel 0-2), or one mask in all three (channel 3: their mean).
#include "common.glsl"
layout(local_size_x = WG_SIZE) in;
layout(push_constant) uniform Push { SegArgs a; } push;
layout(std430, binding = 0) readonly buffer VColorsBuf { float v[]; } v_colours;
layout(std430, binding = 1) buffer ScoresBuf { float v[]; } scores;

void main() {
    uint n = push.a.count;
    for (uint i = gl_GlobalInvocationID.x; i < n; i += gl_NumWorkGroups.x * WG_SIZE) {
        float r = v_colours.v[3 * i], g = v_colours.v[3 * i + 1], b = v_colours.v[3 * i + 2];
        uint c = push.a.channel;
        float s = c == 3u ? (r + g + b) / 3.0 : (c == 0u ? r : (c == 1u ? g : b));
        scores.v[push.a.slot * n + i] += push.a.weight * s;
    }
}
