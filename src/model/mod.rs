//! The in-memory models every stage shares: a plain scene of Gaussians, a camera, and an
//! instanced scene (templates, per-instance transforms and offsets, a background).
pub mod camera;
pub mod instanced;
pub mod scene;
