//! instgs-vk: instanced 3D Gaussian Splatting (InstGS) on Vulkan compute.
//!
//! The modules follow the stages of the main job, and imports only flow down this list
//! (`docs/architecture.md` draws it; `docs/conventions.md` collects the coordinate, camera,
//! SH, quaternion and file conventions):
//!
//! | layer | modules |
//! |---|---|
//! | shared maths and files | [`shared`] (generated from `glsl/common.glsl`), [`math`], [`util`], [`limits`] (confined reads, the memory budget) |
//! | the device | [`gpu`] (context, buffers, recording, kernels) |
//! | in-memory models | [`model`] (scene, camera, instanced scene) |
//! | files and datasets | [`formats`] (PLY, `.instgs`, .spz, SOG, …), [`dataset`] (NeRF-synthetic, COLMAP) |
//! | rendering | [`render`] (upload, rasterizer, backward, sort, level of detail, CPU reference twins) |
//! | training | [`train`] (3DGS optimisation, densification, checkpoints, evaluation, curves) |
//! | InstGS stages | [`segment`] → [`register`] → [`instancing`] (templates, checks, compaction) |
//! | the main job | [`bench`](mod@bench), [`pipeline`] (stages, resume, report) |
//! | viewing | [`player`] |
//!
//! Conventions: world space as stored in the scene; cameras are OpenCV (+X right, +Y down,
//! +Z forward) with `viewmat` world → camera; pixel (0, 0)'s centre is at (0.5, 0.5).

/// Constants and GPU structs generated from `glsl/common.glsl`, plus the SPIR-V of every kernel.
pub mod shared {
    include!(concat!(env!("OUT_DIR"), "/gpu_shared.rs"));
}

pub mod limits;
pub mod math;
pub mod util;

pub mod gpu;

pub mod model;

pub mod dataset;
pub mod formats;

pub mod render;

pub mod train;

pub mod instancing;
pub mod register;
pub mod segment;

pub mod discover;

pub mod bench;
pub mod pipeline;

#[cfg(feature = "player")]
pub mod player;
