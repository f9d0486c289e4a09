// Workgroup-wide exclusive add built on subgroup scans. The number of subgroups per workgroup is
// bounded with the device's minimum subgroup size, passed as specialization constant 0 (never a
// hard-coded 32: lavapipe's subgroups are 8 wide).
#ifndef INSTGS_WG_SCAN_GLSL
#define INSTGS_WG_SCAN_GLSL
#extension GL_KHR_shader_subgroup_basic : require
#extension GL_KHR_shader_subgroup_arithmetic : require

layout(constant_id = 0) const uint MIN_SUBGROUP_SIZE = 4;

shared uint wg_scan_sums[WG_SIZE / MIN_SUBGROUP_SIZE];
shared uint wg_scan_total;

// Exclusive prefix sum of `v` over the workgroup's invocations (in gl_LocalInvocationIndex
// order); `total` receives the sum of all. Every invocation must call it (it has barriers).
uint wg_exclusive_add(uint v, out uint total) {
    uint incl = subgroupInclusiveAdd(v);
    if (gl_SubgroupInvocationID == gl_SubgroupSize - 1) {
        wg_scan_sums[gl_SubgroupID] = incl;
    }
    barrier();
    if (gl_LocalInvocationIndex == 0) {
        uint acc = 0;
        for (uint s = 0; s < gl_NumSubgroups; s++) {
            uint t = wg_scan_sums[s];
            wg_scan_sums[s] = acc;
            acc += t;
        }
        wg_scan_total = acc;
    }
    barrier();
    uint r = wg_scan_sums[gl_SubgroupID] + incl - v;
    total = wg_scan_total;
    barrier();
    return r;
}
#endif
