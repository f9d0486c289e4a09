// The one source of truth for constants and structs shared by the GLSL kernels and Rust.
// build.rs turns every `#define NAME <int>` into a Rust `u32` constant and every struct into a
// `#[repr(C)]` Rust struct (module `instgs_vk::shared`). Descriptor bindings live in the kernels
// and Rust finds them by variable name through SPIR-V reflection.
#ifndef INSTGS_COMMON_GLSL
#define INSTGS_COMMON_GLSL

// Threads per workgroup for one-thread-per-item kernels.
#define WG_SIZE 256
// Screen tiles are TILE_SIZE x TILE_SIZE pixels; blend runs one workgroup per tile.
#define TILE_SIZE 16
// Generic exclusive scan: a workgroup owns SCAN_BLOCK consecutive items; each of its WG_SIZE
// threads SCAN_ITEMS of them, or on CPU devices (KernelPolicy::thread_runs) each of a
// subgroup's threads SCAN_BLOCK / subgroup size, its run a column of the block sums.
#define SCAN_ITEMS 8
#define SCAN_BLOCK 2048
// Radix sort: up to SORT_BITS_* key bits per pass (the bits needed are spread evenly over the
// passes), each thread ranking a run of SORT_ITEMS_* consecutive keys (specialization
// constants 4 and 1 of the sort kernels). GPUs: blocks of SORT_WG threads share one histogram
// column through shared memory, short runs for many workgroups. CPU devices (lavapipe) pay a
// large fixed cost per workgroup that has barriers and per dispatch, and loads cost more than
// arithmetic: every thread's long run is its own histogram column (no shared memory, no
// barrier, workgroups of one subgroup) and wide digits for fewer passes.
#define SORT_BITS_GPU 6
#define SORT_BITS_CPU 8
#define SORT_WG 64
#define SORT_ITEMS_GPU 32
// Inputs of at most the policy's sort_small_max keys are sorted by one workgroup of
// SORT_SMALL_WG threads in one dispatch (sort_small.comp): no fixed cost per pass.
#define SORT_SMALL_WG 16
#define SORT_SMALL_MAX_CPU 12288
#define SORT_ITEMS_CPU 2048
// blend and blend_backward visit the rows a splat reaches with a loop, which on lavapipe skips
// work for real (its `if` only masks lanes). But lavapipe (Mesa 22.3) ends every loop of a
// shader invocation after 65535 iterations of all its loops together
// (LP_MAX_TGSI_LOOP_ITERATIONS). So emit adds up, per tile, the most loop iterations each of its
// splats can cost an invocation (max(1, rows it reaches in the tile, at most
// PIXELS_PER_THREAD) + 1) and a tile whose sum plus BLEND_BATCH_ITERATIONS per batch of 256
// exceeds BLEND_LOOP_ITERATIONS goes to a second pipeline (specialization constant 3,
// CROWDED_TILES) that evaluates every row per splat without a loop, four splats per iteration:
// exact up to ~200 000 splats in a tile on lavapipe (each 256-splat batch also costs the loop
// that loads it) and without limit elsewhere.
#define BLEND_LOOP_ITERATIONS 60000
#define BLEND_BATCH_ITERATIONS 20
// The draw path (splat_quads.vert) draws every splat as an instance: a 4-vertex triangle strip.
#define QUAD_VERTICES 4
// Indirect dispatches are clamped to this many workgroups; kernels loop grid-stride.
#define MAX_GROUPS 65535

// Slots of the `counts` buffer (GPU-written sizes that later passes read).
#define COUNT_GAUSSIANS 0
#define COUNT_VISIBLE 1
#define COUNT_ISECT 2
#define COUNT_ISECT_NEEDED 3
#define COUNT_SORT 4
#define COUNT_INSTANCES 5
#define COUNT_SPLATS_NEEDED 6
#define COUNT_SLOTS 8

// Each count slot owns ARGS_PER_SLOT VkDispatchIndirectCommand entries (3 uints each):
#define ARGS_ITEMS 0
#define ARGS_SORT_BLOCKS 1
#define ARGS_SCAN_BLOCKS 2
#define ARGS_SORT_SMALL 3
#define ARGS_SORT_SCAN 4
#define ARGS_PER_SLOT 5

// Input modes of the generic scan.
#define SCAN_MODE_VALUE 0
#define SCAN_MODE_NONZERO 1
#define SCAN_MODE_GATHER 2

#define NO_SLOT 0xFFFFFFFF

/// Per-frame camera and image parameters, a small buffer that kernels read as RGBA32UI texels
/// (frame.glsl, 12 texels). Not a uniform buffer: with one, lavapipe (Mesa 22.3) grew the
/// process by ~0.4 MB per frame in the preprocess pass whatever the scene size (measured;
/// probably its uniform inlining, which compiles shader variants from uniform values that steer
/// loops).
/// Camera is OpenCV: +X right, +Y down, +Z forward; viewmat maps world to camera.
struct FrameParams {
    mat4 viewmat; // world -> camera, column-major
    vec4 intrinsics; // fx, fy, cx, cy in pixels; pixel (0,0) centre at (0.5, 0.5)
    vec4 campos; // camera centre in world space (w unused)
    vec4 background; // rgb background colour (a unused)
    uint width; // image width in pixels
    uint height; // image height in pixels
    uint tiles_x; // ceil(width / TILE_SIZE)
    uint tiles_y; // ceil(height / TILE_SIZE)
    uint num_gaussians; // N splats: background Gaussians, then every (template Gaussian, instance) pair
    uint sh_degree; // SH degree evaluated (0..3)
    uint sh_coeffs; // SH coefficients stored per Gaussian and channel ((degree+1)^2 of the scene)
    uint isect_capacity; // length of the intersection buffers
    float near_plane; // Gaussians with camera z <= near_plane are culled
    float far_plane; // and with z > far_plane
    uint num_background; // splats [0, num_background) are plain Gaussians (parameter row = splat)
    uint num_groups; // instanced groups in the `groups` buffer (0 for a plain scene)
    uint num_rows; // parameter rows: background Gaussians, then every group's template Gaussians
    uint xform_grads; // 1: preprocess_backward also writes the instance-transform gradient terms
    uint select; // 1: instance_select culled instances and chose their levels this frame; the
                 // splats after the background are the selected instances' Gaussians, packed
                 // (see preprocess.comp). 0: every (template Gaussian, instance) pair, fixed order.
    uint num_instances; // instances of all groups (rows of the `xforms` buffer)
    uint offset_storage; // OFFSETS_F32, OFFSETS_PQ8 or OFFSETS_F16 (instance.glsl)
    uint num_visible; // visible Gaussians: copied on the GPU from counts before the backward
                      // pass of a plain scene (preprocess_backward's VISIBLE_ROWS); 0 otherwise
    float tile_cost_weight; // training's frame-cost regulariser (preprocess_backward): each
                            // visible splat's three log-scales get this times its tiles touched
                            // added to their gradient; 0: off (and never read when rendering)
    uint _pad2;
};

/// One instanced group (paper section 5.3: groups concatenated with start/length tables). Its
/// splats are [splat_first, splat_first + rows * instances), instance-major: splat
/// splat_first + k * rows + j is template Gaussian j (parameter row row_first + j) placed by
/// instance k (transform instance_first + k); its offsets live at pair index
/// splat - num_background of the offset buffers. Those are level 0, the template itself. A
/// scene uploaded with level of detail also holds coarser levels l = 1.. of every template:
/// level_rows[l] Gaussians at parameter rows level_row_first[l].., offsets instance-major at
/// pair index level_pair_first[l] + k * level_rows[l] + j (after every group's level-0 pairs).
struct GroupInfo {
    uint splat_first;
    uint row_first;
    uint rows; // template Gaussians (level 0)
    uint instances; // K
    uint instance_first;
    uint levels; // levels stored, 1..LOD_LEVELS (1: the template only)
    uint _pad0;
    uint _pad1;
    uvec4 level_row_first; // [0] = row_first
    uvec4 level_rows; // [0] = rows
    uvec4 level_pair_first; // [0] = splat_first - num_background
    vec4 bound; // template-space bounding sphere of the Gaussians' 3-sigma extents: centre, radius
};

// How a scene's per-pair offsets are held on the device (FrameParams.offset_storage):
// f32 arrays d_means, d_sh0, d_opacities (28 bytes per pair; training writes them); product-quantised
// codes in d_codes with codebooks (2 bytes per pair, crate::formats::pq8); or seven halves per pair
// packed into d_codes (14 bytes per pair: dp xyz, d SH DC rgb, d opacity logit).
#define OFFSETS_F32 0
#define OFFSETS_PQ8 1
#define OFFSETS_F16 2
// Halves per pair in OFFSETS_F16.
#define OFFSET_HALVES 7

// Level-of-detail levels per template at most, the template (level 0) included.
#define LOD_LEVELS 4

/// Push constants of instance_select.comp.
struct SelectArgs {
    uint max_level; // coarsest level allowed (0: exact rendering, culling only)
    float splats_per_pixel; // the LOD quality knob: a level is used while it keeps at least this
                            // many Gaussians per pixel of the instance's projected bounding disc
    float margin_px; // frustum test margin in pixels (the 2D low-pass filter's spill)
    uint _pad0;
};

// Transform-gradient terms per (template Gaussian, instance) pair, summed per instance by
// xform_grad_reduce: dL/dt (3), dL/d ln s (1), dL/dR (9, column-major) and dL/dq_R through the
// rotation composition q_R * q (4, for the unit quaternion).
#define XFORM_GRAD_TERMS 17

// Camera-gradient terms of a plain scene's frame, summed per preprocess_backward workgroup, then by
// camera_grad_reduce:
// dL/dW (9, column-major) and dL/dt (3) of viewmat = [W | t] with the camera centre held, then
// dL/dcampos (3) through the SH view direction (the host chains campos = -W^T t).
#define CAMERA_GRAD_TERMS 15

/// An instance's template -> world similarity p_world = s R p_template + t (then + offset).
struct InstanceXform {
    mat4 transform; // [s R | t], column-major
    vec4 quat; // R as a unit (w, x, y, z) quaternion; Gaussian rotations become quat * q
    vec4 scale; // s, ln s, largest |dp| of the instance's offsets (world units), 0; Gaussian
                // log-scales gain ln s
};

/// Push constants of the generic scan kernels.
struct ScanArgs {
    uint count_slot; // counts[count_slot] = number of items
    uint mode; // SCAN_MODE_*
    uint out_slot; // counts[out_slot] <- total, or NO_SLOT
    uint clamp_slot; // counts[clamp_slot] <- min(total, capacity), or NO_SLOT
    uint capacity; // capacity for clamp_slot
    uint divisor; // scan_blocks: length = ceil(count / divisor) * multiplier
    uint multiplier;
    uint out_bias; // added to the total written to out_slot and clamp_slot
};

/// Push constants of the radix sort kernels.
struct SortArgs {
    uint count_slot; // counts[count_slot] = number of keys
    uint shift; // first key bit of this pass
    uint bits; // key bits of this pass (1..SORT_BITS_*)
    uint _pad0;
};

/// Push constants of the indirect-argument writer.
struct DispatchArgs {
    uint count_slot; // reads counts[count_slot], writes args[count_slot * ARGS_PER_SLOT + k]
    uint sort_block; // keys per radix-sort workgroup (threads * items)
    uint sort_small_max; // up to this many keys: the one-dispatch sort (sort_small.comp)
    uint _pad2;
};

/// Push constants of the loss kernels (loss_*.comp).
struct LossArgs {
    uint width;
    uint height;
    float ssim_weight; // lambda of (1 - lambda) L1 + lambda (1 - SSIM); Inria: 0.2
    float inv_count; // 1 / (3 width height): both terms are means over pixels and channels
};

/// Push constants of the Adam step (adam.comp over floats, adam_vec4.comp over vec4s),
/// torch.optim.Adam's update with the bias corrections precomputed on the host.
struct AdamArgs {
    uint count; // elements updated (floats or vec4s), from `first` on
    uint stride; // elements per row (the rows of a parameter group's Gaussians, or 1)
    uint head; // the first `head` parameters (floats) of every row use lr_head, the rest lr_tail
    float lr_head;
    float lr_tail;
    float beta1;
    float beta2;
    float eps;
    float inv_bias1; // 1 / (1 - beta1^step)
    float inv_sqrt_bias2; // 1 / sqrt(1 - beta2^step)
    uint first; // adam.comp: the first float updated; adam_vec4.comp always starts at 0
    uint _pad0;
};

/// Push constants of seg_accumulate (gradient-driven segmentation, InstGS Eq. 3).
struct SegArgs {
    uint count; // splats
    uint slot; // scores[slot * count + i]
    float weight; // 1 for an instance mask, -alpha for the all-pixels pass
    uint channel; // 0-2: the mask that colour channel carried; 3: one mask in every channel (their mean)
};

/// Push constants of present.comp (the player's copy of a frame into a swapchain image).
struct PresentArgs {
    uint width; // image width in pixels
    uint height; // image height in pixels
    uint overlay_width; // the overlay covers pixels x < overlay_width, y < overlay_height
    uint overlay_height; // (0: no overlay)
    uint bgra; // 1: pack as B8G8R8A8, 0: as R8G8B8A8
    uint srgb_decode; // 1: the swapchain format is _SRGB (it encodes on write), so decode first
    uint _pad0;
    uint _pad1;
};

/// Push constants of the per-photo colour transform (appearance.comp and its backward
/// appearance_backward.comp): out = M rgb + b, the 3x4 affine of Hierarchical 3DGS's exposure
/// compensation, applied to a rendered image before the loss. Row c is (M[c][0..2], b[c]).
struct AppearanceArgs {
    vec4 row0;
    vec4 row1;
    vec4 row2;
    // The lens's vignetting, a falloff v = 1 + k1 r^2 + k2 r^4 that multiplies the transformed
    // colour, r^2 = ((x + 0.5 - cx) / fx)^2 + ((y + 0.5 - cy) / fy)^2 at pixel (x, y):
    // (k1, k2, 0, 0) and (cx, cy, 1 / fx, 1 / fy) in pixels.
    vec4 vignetting;
    vec4 pinhole;
    uint pixels; // width * height
    uint width;
    uint _pad1;
    uint _pad2;
};
// Pixels per appearance invocation (a run, so the backward's sums are added per run, not per pixel).
#define APPEARANCE_RUN 16
// The backward's gradient sums: dL/dM row-major then dL/db (APPEARANCE_PARAMS floats), the same
// order as the parameters (row c: M[c][0..2], b[c]).
#define APPEARANCE_PARAMS 12
// ... followed by dL/dk1 and dL/dk2 of the vignetting: APPEARANCE_GRADS floats in all.
#define APPEARANCE_GRADS 14

// SSIM window: 11 x 11 Gaussian, sigma 1.5 (Wang et al. 2004; Inria's loss_utils.ssim), zero
// padding at the image border as torch's conv2d with padding 5.
#define SSIM_RADIUS 5
// Each loss invocation filters a run of LOSS_RUN pixels along the filter direction, so every
// input is loaded once per run instead of once per tap (loads dominate on lavapipe).
#define LOSS_RUN 16
// Planes of the SSIM intermediates: 5 window moments (x, y, x^2, y^2, xy) and 3 cotangents,
// each per colour channel: plane (q * 3 + c) of width * height floats.
#define SSIM_MOMENTS 5
#define SSIM_COTANGENTS 3
// Slots of the loss buffer: sums over pixels and channels of |x - y| and of SSIM.
#define LOSS_L1 0
#define LOSS_SSIM 1
#define LOSS_SLOTS 4

#endif
