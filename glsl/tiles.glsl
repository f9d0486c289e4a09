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

// Half extents in pixels (x, y) of the region where a splat's alpha = o exp(power) reaches
// 1/255, for co = (conic a, b, c, opacity o), power = -(a dx^2 + c dy^2) / 2 - b dx dy:
// |dx| <= sqrt(2 ln(255 o) Sigma_xx), |dy| <= sqrt(2 ln(255 o) Sigma_yy) with
// Sigma = [[c, -b], [-b, a]] / (a c - b^2) (the largest power along a row or column). Exact up
// to a 0.1 % + 0.001 px margin for rounding: blend and blend_backward skip what lies beyond.
vec2 splat_reach(vec4 co) {
    float k = max(2.0 * log(255.0 * co.w), 0.0) / max(co.x * co.z - co.y * co.y, 1e-30);
    return sqrt(k * co.zx) * 1.001 + 0.001;
}

// Whether splat (xy, co) can reach alpha >= 1/255 at a pixel centre of tile `tile`: the least
// q(d) = a dx^2 + 2 b dx dy + c dy^2 (= -2 power) over the rectangle of the tile's pixel
// centres against 2 ln(255 o), with a margin (0.1 % + 0.001) above blend's own cut (q <=
// 2 ln(255 o) + 2e-4). Zero where the rectangle holds the mean; else the least q lies on an
// edge, where q is a parabola minimised in closed form. The tile rectangle keeps the tiles of
// the ellipse's bounding box; this drops those of the box's corners that an oblique ellipse
// misses (Speedy-Splat's AccuTile, Hanson et al. 2025, here exact). `precise` (no fused
// multiply-adds): preprocess counts and emit lists the same tiles. CPU twin: cpu::splat_hits_tile.
bool splat_hits_tile(vec2 xy, vec4 co, ivec2 tile) {
    precise vec2 lo = vec2(tile * int(TILE_SIZE)) + 0.5 - xy;
    precise vec2 hi = lo + float(TILE_SIZE - 1);
    precise float q = 0.0;
    if (lo.x > 0.0 || hi.x < 0.0 || lo.y > 0.0 || hi.y < 0.0) {
        q = 3.0e38;
        for (int e = 0; e < 2; e++) {
            precise float x = e == 0 ? lo.x : hi.x;
            precise float dy = clamp(-co.y * x / co.z, lo.y, hi.y);
            q = min(q, co.x * x * x + 2.0 * co.y * x * dy + co.z * dy * dy);
            precise float y = e == 0 ? lo.y : hi.y;
            precise float dx = clamp(-co.y * y / co.x, lo.x, hi.x);
            q = min(q, co.x * dx * dx + 2.0 * co.y * dx * y + co.z * y * y);
        }
    }
    precise float lim = max(2.0 * log(255.0 * co.w), 0.0) * 1.001 + 0.001;
    return q <= lim;
}

// The first and last of `rows` pixel rows (centres row0, row0 + 1, ...) within reach_y of a
// splat centred at height y; last < first where it reaches none.
ivec2 splat_rows(float y, float reach_y, float row0, uint rows) {
    return ivec2(clamp(ceil(y - reach_y - row0), 0.0, float(rows)),
                 clamp(floor(y + reach_y - row0), -1.0, float(rows) - 1.0));
}

// The most loop iterations splat (xy, co) can cost one blend invocation of tile row `ty`
// holding `rows` (PIXELS_PER_THREAD) pixel rows: max(1, rows of the tile it reaches, at most
// `rows`) + 1 (see BLEND_LOOP_ITERATIONS).
uint blend_cost(vec2 xy, vec4 co, uint ty, uint rows) {
    ivec2 r = splat_rows(xy.y, splat_reach(co).y, float(ty * TILE_SIZE) + 0.5, TILE_SIZE);
    return uint(clamp(r.y - r.x + 1, 1, int(rows))) + 1;
}

// Whether a tile of `splats` splats whose blend_cost sum is `cost` could exceed lavapipe's loop
// budget in blend's row loops (BLEND_LOOP_ITERATIONS).
bool blend_tile_crowded(uint cost, uint splats) {
    return cost + BLEND_BATCH_ITERATIONS * (splats / 256 + 2) > BLEND_LOOP_ITERATIONS;
}
#endif
