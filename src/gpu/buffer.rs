//! A Vulkan buffer with its memory (gpu-allocator), host-visible or device-local.
use std::sync::Arc;

use anyhow::{anyhow, bail, Result};
use ash::vk;
use gpu_allocator::vulkan::Allocation;

use crate::gpu::context::Gpu;
use gpu_allocator::vulkan::{AllocationCreateDesc, AllocationScheme};
use gpu_allocator::MemoryLocation;

/// A Vulkan buffer with its memory. Freed on drop.
pub struct Buffer {
    pub(crate) gpu: Arc<Gpu>,
    pub raw: vk::Buffer,
    pub(crate) alloc: Option<Allocation>,
    pub size: u64,
    pub name: String,
    /// Views of its whole length as texels of a format, for kernels that read it as a
    /// `samplerBuffer` ([`Buffer::texel_view`]); made on first use.
    pub(crate) views: std::sync::Mutex<Vec<(vk::Format, vk::BufferView)>>,
}

impl Buffer {
    /// Writes `data` at the start of a host-visible buffer.
    pub fn write_mapped<T: bytemuck::Pod>(&mut self, data: &[T]) -> Result<()> {
        let bytes: &[u8] = bytemuck::cast_slice(data);
        let m = self.mapped_mut()?;
        if bytes.len() > m.len() {
            bail!("writing {} bytes into a {}-byte buffer", bytes.len(), m.len());
        }
        m[..bytes.len()].copy_from_slice(bytes);
        Ok(())
    }

    /// Reads `count` elements from the start of a host-visible buffer.
    pub fn read_mapped<T: bytemuck::Pod>(&self, count: usize) -> Result<Vec<T>> {
        let m = self.mapped()?;
        let bytes = count * std::mem::size_of::<T>();
        if bytes > m.len() {
            bail!("reading {bytes} bytes from a {}-byte buffer", m.len());
        }
        Ok(bytemuck::pod_collect_to_vec(&m[..bytes]))
    }

    /// The buffer as texels of `format` (RGBA32F or RGBA32UI: a uniform texel buffer view of its
    /// whole length, the last texel padded), made on first use and kept until the buffer
    /// is dropped. Storage buffers carry the usage for it.
    pub(crate) fn texel_view(&self, format: vk::Format) -> Result<vk::BufferView> {
        let mut views = self.views.lock().unwrap();
        if let Some(&(_, v)) = views.iter().find(|(f, _)| *f == format) {
            return Ok(v);
        }
        let texels = self.size.div_ceil(16); // the buffer underneath is padded to whole texels
        if texels > self.gpu.info.max_texel_buffer_elements {
            bail!(
                "buffer '{}' ({texels} texels) exceeds the device's maxTexelBufferElements ({})",
                self.name,
                self.gpu.info.max_texel_buffer_elements
            );
        }
        let info = vk::BufferViewCreateInfo::default().buffer(self.raw).format(format).offset(0).range(texels * 16);
        let v = unsafe { self.gpu.device.create_buffer_view(&info, None)? };
        views.push((format, v));
        Ok(v)
    }

    pub(crate) fn mapped(&self) -> Result<&[u8]> {
        self.alloc
            .as_ref()
            .and_then(|a| a.mapped_slice())
            .ok_or_else(|| anyhow!("buffer '{}' is not host-visible", self.name))
    }

    pub(crate) fn mapped_mut(&mut self) -> Result<&mut [u8]> {
        let name = self.name.clone();
        self.alloc
            .as_mut()
            .and_then(|a| a.mapped_slice_mut())
            .ok_or_else(|| anyhow!("buffer '{name}' is not host-visible"))
    }
}

impl Drop for Buffer {
    fn drop(&mut self) {
        if let Some(a) = self.alloc.take() {
            let _ = self.gpu.allocator.lock().unwrap().free(a);
        }
        unsafe {
            for &(_, v) in self.views.get_mut().unwrap().iter() {
                self.gpu.device.destroy_buffer_view(v, None);
            }
            self.gpu.device.destroy_buffer(self.raw, None)
        };
    }
}

impl Gpu {
    /// Creates a buffer. Zero-size requests get a 16-byte buffer (Vulkan forbids size 0).
    pub fn buffer(
        self: &Arc<Self>,
        name: &str,
        size: u64,
        usage: vk::BufferUsageFlags,
        location: MemoryLocation,
    ) -> Result<Buffer> {
        let size = size.max(16);
        // Whole 16-byte texels underneath, so a texel view (`texel_view`) covers every byte of
        // `size`; the padding is never read or written as data.
        let raw_size = size.next_multiple_of(16);
        let mut usage = usage | vk::BufferUsageFlags::TRANSFER_SRC | vk::BufferUsageFlags::TRANSFER_DST;
        if usage.contains(vk::BufferUsageFlags::STORAGE_BUFFER) {
            usage |= vk::BufferUsageFlags::UNIFORM_TEXEL_BUFFER;
        }
        let raw =
            unsafe { self.device.create_buffer(&vk::BufferCreateInfo::default().size(raw_size).usage(usage), None)? };
        let requirements = unsafe { self.device.get_buffer_memory_requirements(raw) };
        let alloc = self.allocator.lock().unwrap().allocate(&AllocationCreateDesc {
            name,
            requirements,
            location,
            linear: true,
            allocation_scheme: AllocationScheme::GpuAllocatorManaged,
        });
        let alloc = match alloc {
            Ok(a) => a,
            Err(e) => {
                unsafe { self.device.destroy_buffer(raw, None) };
                return Err(anyhow!("cannot allocate {size} bytes for buffer '{name}': {e}"));
            }
        };
        unsafe { self.device.bind_buffer_memory(raw, alloc.memory(), alloc.offset())? };
        Ok(Buffer {
            gpu: self.clone(),
            raw,
            alloc: Some(alloc),
            size,
            name: name.to_string(),
            views: std::sync::Mutex::new(Vec::new()),
        })
    }
}
