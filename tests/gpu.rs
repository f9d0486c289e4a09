//! The Vulkan context: validation messages reach the tests, device selection errors are clear.
mod common;
use ash::vk;
use common::*;
use instgs_vk::gpu::{Gpu, GpuOptions};

#[test]
fn validation_layer_reports_misuse() {
    // A separate instance so this deliberate error cannot leak into other tests.
    let opts = GpuOptions { validation: true, ..Default::default() };
    let gpu = Gpu::new(&opts).unwrap();
    let info = vk::BufferCreateInfo::default().size(0).usage(vk::BufferUsageFlags::STORAGE_BUFFER);
    // Size 0 violates VUID-VkBufferCreateInfo-size-00912.
    if let Ok(b) = unsafe { gpu.device.create_buffer(&info, None) } {
        unsafe { gpu.device.destroy_buffer(b, None) };
    }
    let m = gpu.take_validation_messages();
    assert!(m.iter().any(|s| s.contains("00912")), "expected a validation error, got {m:?}");
}

#[test]
fn device_selection() {
    let (gpu, _) = gpu();
    assert!(gpu.info.subgroup_size >= 1 && gpu.info.min_subgroup_size <= gpu.info.subgroup_size);
    let by_index =
        Gpu::new(&GpuOptions { device: Some("0".into()), validation: true, echo_messages: true, ..Default::default() })
            .unwrap();
    assert!(!by_index.info.name.is_empty());
    let e = Gpu::new(&GpuOptions { device: Some("no-such-device".into()), ..Default::default() }).err().unwrap();
    assert!(e.to_string().contains("no Vulkan device matches 'no-such-device'"), "{e}");
    let e = Gpu::new(&GpuOptions { device: Some("99".into()), ..Default::default() }).err().unwrap();
    assert!(e.to_string().contains("out of range"), "{e}");
    assert_clean(&by_index);
}
