//! instgs-vk: instanced 3D Gaussian Splatting (InstGS) on Vulkan compute.
//!
//! Conventions: world space as stored in the scene; cameras are OpenCV (+X right, +Y down,
//! +Z forward) with `viewmat` world → camera; pixel (0, 0)'s centre is at (0.5, 0.5).

/// Constants and GPU structs generated from `glsl/common.glsl`, plus the SPIR-V of every kernel.
pub mod shared {
    include!(concat!(env!("OUT_DIR"), "/gpu_shared.rs"));
}

pub mod camera;
pub mod codes;
pub mod compact;
pub mod config;
pub mod cpu;
pub mod dataset;
pub mod formats;
pub mod gpu;
pub mod grad;
pub mod instance;
pub mod instgs;
pub mod kernels;
pub mod lod;
pub mod optim;
pub mod overlay;
pub mod player;
pub mod plot;
pub mod raster;
pub mod register;
pub mod scene;
pub mod segment;
pub mod sort;
pub mod template;
pub mod train;
pub mod util;
pub mod verify;
