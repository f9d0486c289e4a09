//! Vulkan context on `ash` + `gpu-allocator`: device choice, validation layers, buffers,
//! compute kernels with reflected descriptor layouts (storage and uniform buffers, and texel
//! buffers: RGBA32F or RGBA32UI views of storage buffers), the draw path's graphics pipelines, command
//! recording and GPU timestamps.
//!
//! Device choice: a discrete GPU over an integrated one over a virtual one over a CPU device
//! (lavapipe). `INSTGS_DEVICE` or `--device NAME|INDEX` overrides (a name matches by
//! case-insensitive substring). `INSTGS_VALIDATION=1` enables `VK_LAYER_KHRONOS_validation`
//! with synchronization validation; its warnings and errors are collected (see
//! [`Gpu::take_validation_messages`]) and echoed to stderr. `INSTGS_POISON=1` fills every new
//! device-local storage buffer with 0xffffffff (a NaN as f32, the largest u32), so a run that
//! reads memory nothing wrote differs from one without it (tests compare the two).

pub mod buffer;
pub mod context;
pub mod draw;
pub mod kernel;
pub mod kernels;
pub mod record;
pub mod swapchain;

pub use buffer::Buffer;
pub use context::{DeviceInfo, Gpu, GpuOptions, Surface};
pub use kernel::Kernel;
pub use record::{CommandBuffer, Recorder, Timer};
