//! Rendering: scene upload, the forward rasterizer and its backward recording, the GPU radix
//! sort, level of detail, and the CPU reference twins every kernel is tested against.
pub mod appearance;
pub mod frames;
pub mod lod;
pub mod raster;
pub mod reference;
pub mod sort;
pub mod upload;
