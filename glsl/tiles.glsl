// The screen tiles a splat touches: every tile holding a pixel centre within `radius` (per
// axis) of the projected mean, as [lo, hi). Conservative like gsplat's floor/ceil; Inria's
// getRect truncates (p + r + 15) / 16 as a float and can miss the last partly covered tile.
#ifndef INSTGS_TILES_GLSL
#define INSTGS_TILES_GLSL
void tile_rect(vec2 xy, uvec2 radius, uvec2 grid, out ivec2 lo, out ivec2 hi) {
    vec2 r = vec2(radius);
    vec2 g = vec2(grid);
    // Pixel px's centre is at px + 0.5. Clamp before converting: far splats project anywhere.
    lo = ivec2(clamp(floor((xy - r - 0.5) / float(TILE_SIZE)), vec2(0.0), g));
    hi = ivec2(clamp(floor((xy + r - 0.5) / float(TILE_SIZE)) + 1.0, vec2(0.0), g));
}
#endif
