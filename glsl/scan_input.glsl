// Input of the generic scan: counts, the input values and an optional gather list.
#ifndef INSTGS_SCAN_INPUT_GLSL
#define INSTGS_SCAN_INPUT_GLSL
layout(push_constant) uniform Push { ScanArgs args; };
layout(std430, binding = 0) buffer CountsBuf { uint v[]; } counts;
layout(std430, binding = 1) readonly buffer ScanInBuf { uint v[]; } scan_in;
layout(std430, binding = 2) readonly buffer GatherBuf { uint v[]; } gather;

uint scan_value(uint idx) {
    if (args.mode == SCAN_MODE_NONZERO) return scan_in.v[idx] != 0 ? 1 : 0;
    if (args.mode == SCAN_MODE_GATHER) return scan_in.v[gather.v[idx]];
    return scan_in.v[idx];
}
#endif
