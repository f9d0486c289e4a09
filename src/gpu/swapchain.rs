//! The window's swapchain and the present step: `present.comp` packs the rendered image (plus
//! an optional text overlay) into 8-bit texels that are copied into the acquired swapchain
//! image. Formats: 8-bit UNORM first, _SRGB accepted (values decoded first); present modes:
//! immediate, else mailbox, else FIFO without vsync, FIFO with it.
use anyhow::Context;
use std::sync::Arc;

use anyhow::{anyhow, bail, Result};
use ash::vk;
use gpu_allocator::MemoryLocation;

use crate::gpu::kernels::Kernels;
use crate::gpu::{Buffer, CommandBuffer, Gpu};
use crate::shared::*;

pub struct Swapchain {
    raw: vk::SwapchainKHR,
    images: Vec<vk::Image>,
    pub extent: vk::Extent2D,
    bgra: bool,
    srgb: bool,
    /// The images allow TRANSFER_SRC: screenshots copy the presented image itself.
    readable: bool,
    /// Signalled when an image's commands finish; its presentation waits on it.
    render_done: Vec<vk::Semaphore>,
}

/// The swapchain and the per-frame present step.
pub struct Presenter {
    gpu: Arc<Gpu>,
    k: Arc<Kernels>,
    pub swapchain: Option<Swapchain>,
    cmd: CommandBuffer,
    acquired: vk::Semaphore,
    texels: Option<Buffer>,
    screenshot: Option<Buffer>,
    pub vsync: bool,
    /// The swapchain must be recreated (resize, out of date, suboptimal, vsync toggled).
    pub stale: bool,
}

fn surface(gpu: &Gpu) -> Result<&crate::gpu::Surface> {
    gpu.surface.as_ref().ok_or_else(|| anyhow!("the device was opened without a window surface"))
}

impl Presenter {
    pub fn new(gpu: &Arc<Gpu>, k: &Arc<Kernels>, vsync: bool) -> Result<Presenter> {
        let acquired = unsafe { gpu.device.create_semaphore(&vk::SemaphoreCreateInfo::default(), None)? };
        Ok(Presenter {
            gpu: gpu.clone(),
            k: k.clone(),
            swapchain: None,
            cmd: CommandBuffer::new(gpu)?,
            acquired,
            texels: None,
            screenshot: None,
            vsync,
            stale: true,
        })
    }

    /// (Re)creates the swapchain for a window of `size`; false while the window has no area.
    pub fn recreate(&mut self, size: vk::Extent2D) -> Result<bool> {
        let gpu = self.gpu.clone();
        let s = surface(&gpu)?;
        unsafe { gpu.device.device_wait_idle()? };
        let caps = unsafe { s.loader.get_physical_device_surface_capabilities(gpu.physical, s.raw)? };
        let extent = if caps.current_extent.width != u32::MAX {
            caps.current_extent
        } else {
            vk::Extent2D {
                width: size.width.clamp(caps.min_image_extent.width, caps.max_image_extent.width),
                height: size.height.clamp(caps.min_image_extent.height, caps.max_image_extent.height),
            }
        };
        if extent.width == 0 || extent.height == 0 {
            return Ok(false);
        }
        if !caps.supported_usage_flags.contains(vk::ImageUsageFlags::TRANSFER_DST) {
            bail!("the window surface does not accept transfer writes (TRANSFER_DST), which the player needs");
        }
        let formats = unsafe { s.loader.get_physical_device_surface_formats(gpu.physical, s.raw)? };
        let (format, bgra, srgb) = choose_format(&formats)?;
        let modes = unsafe { s.loader.get_physical_device_surface_present_modes(gpu.physical, s.raw)? };
        let mode = choose_present_mode(&modes, self.vsync);
        let mut count = caps.min_image_count + 1;
        if caps.max_image_count > 0 {
            count = count.min(caps.max_image_count);
        }
        let readable = caps.supported_usage_flags.contains(vk::ImageUsageFlags::TRANSFER_SRC);
        let mut usage = vk::ImageUsageFlags::TRANSFER_DST;
        if readable {
            usage |= vk::ImageUsageFlags::TRANSFER_SRC;
        }
        let alpha = [
            vk::CompositeAlphaFlagsKHR::OPAQUE,
            vk::CompositeAlphaFlagsKHR::INHERIT,
            vk::CompositeAlphaFlagsKHR::PRE_MULTIPLIED,
            vk::CompositeAlphaFlagsKHR::POST_MULTIPLIED,
        ]
        .into_iter()
        .find(|a| caps.supported_composite_alpha.contains(*a))
        .unwrap_or(vk::CompositeAlphaFlagsKHR::OPAQUE);
        let old = self.swapchain.take();
        let ci = vk::SwapchainCreateInfoKHR::default()
            .surface(s.raw)
            .min_image_count(count)
            .image_format(format.format)
            .image_color_space(format.color_space)
            .image_extent(extent)
            .image_array_layers(1)
            .image_usage(usage)
            .image_sharing_mode(vk::SharingMode::EXCLUSIVE)
            .pre_transform(caps.current_transform)
            .composite_alpha(alpha)
            .present_mode(mode)
            .clipped(true)
            .old_swapchain(old.as_ref().map_or(vk::SwapchainKHR::null(), |o| o.raw));
        let raw = unsafe { s.swapchain.create_swapchain(&ci, None) }.context("cannot create the swapchain");
        if let Some(o) = old {
            self.destroy(o);
        }
        let raw = raw?;
        let images = unsafe { s.swapchain.get_swapchain_images(raw)? };
        let render_done = images
            .iter()
            .map(|_| unsafe { gpu.device.create_semaphore(&vk::SemaphoreCreateInfo::default(), None) })
            .collect::<std::result::Result<Vec<_>, _>>()?;
        let pixels = extent.width as u64 * extent.height as u64;
        self.texels = Some(gpu.storage("present-texels", pixels * 4)?);
        self.screenshot = Some(gpu.buffer("screenshot", pixels * 4, Default::default(), MemoryLocation::GpuToCpu)?);
        eprintln!(
            "swapchain {}x{} {:?} {:?}, {} images",
            extent.width,
            extent.height,
            format.format,
            mode,
            images.len()
        );
        self.swapchain = Some(Swapchain { raw, images, extent, bgra, srgb, readable, render_done });
        self.stale = false;
        Ok(true)
    }

    fn destroy(&self, sc: Swapchain) {
        unsafe {
            for s in sc.render_done {
                self.gpu.device.destroy_semaphore(s, None);
            }
            if let Some(s) = &self.gpu.surface {
                s.swapchain.destroy_swapchain(sc.raw, None);
            }
        }
    }

    /// The next swapchain image; `None` (and the swapchain marked stale) when it is out of date.
    pub fn acquire(&mut self) -> Result<Option<u32>> {
        let s = surface(&self.gpu)?;
        let sc = self.swapchain.as_ref().unwrap();
        match unsafe { s.swapchain.acquire_next_image(sc.raw, u64::MAX, self.acquired, vk::Fence::null()) } {
            Ok((index, suboptimal)) => {
                self.stale |= suboptimal;
                Ok(Some(index))
            }
            Err(vk::Result::ERROR_OUT_OF_DATE_KHR) => {
                self.stale = true;
                Ok(None)
            }
            Err(e) => Err(device_error("acquiring a swapchain image", e)),
        }
    }

    /// Packs `image` into swapchain image `index` and presents it; with `screenshot`, also
    /// returns the presented pixels as RGBA8.
    pub fn present(
        &mut self,
        index: u32,
        image: &Buffer,
        overlay: Option<((u32, u32), &Buffer)>,
        screenshot: bool,
    ) -> Result<Option<(u32, u32, Vec<u8>)>> {
        let gpu = self.gpu.clone();
        let s = surface(&gpu)?;
        let sc = self.swapchain.as_ref().unwrap();
        let target = sc.images[index as usize];
        let texels = self.texels.as_ref().unwrap();
        let shot_buf = self.screenshot.as_ref().unwrap();
        let ext = sc.extent;
        let (ow, oh) = overlay.map_or((0, 0), |((w, h), _)| (w.min(ext.width), h.min(ext.height)));
        let args = PresentArgs {
            width: ext.width,
            height: ext.height,
            overlay_width: ow,
            overlay_height: oh,
            bgra: sc.bgra as u32,
            srgb_decode: sc.srgb as u32,
            ..Default::default()
        };
        let overlay_buf = overlay.map_or(texels, |(_, b)| b);
        let args = if overlay.is_some_and(|((w, _), _)| w > ext.width) {
            // A window narrower than the overlay: no overlay (its rows would not line up).
            PresentArgs { overlay_width: 0, overlay_height: 0, ..args }
        } else {
            args
        };
        let pixels = ext.width * ext.height;
        let k = &self.k;
        let read_image = screenshot && sc.readable;
        self.cmd.record(|rec| {
            rec.dispatch(
                &k.present,
                &[("image", image), ("overlay", overlay_buf), ("texels", texels)],
                &args,
                [pixels.div_ceil(WG_SIZE).min(MAX_GROUPS), 1, 1],
            )?;
            copy_to_image(&gpu.device, rec.raw(), texels, target, ext, read_image.then_some(shot_buf));
            if screenshot && !sc.readable {
                // The surface cannot be read: save the texels that were copied into it.
                rec.copy(texels, shot_buf, pixels as u64 * 4);
            }
            Ok(())
        })?;
        let signal = sc.render_done[index as usize];
        self.cmd
            .submit_and_wait_sync(&[(self.acquired, vk::PipelineStageFlags::TRANSFER)], &[signal])
            .map_err(|e| anyhow!("presenting a frame: {e:#}"))?;
        let swapchains = [sc.raw];
        let indices = [index];
        let waits = [signal];
        let info =
            vk::PresentInfoKHR::default().wait_semaphores(&waits).swapchains(&swapchains).image_indices(&indices);
        match gpu.with_queue(|q| unsafe { s.swapchain.queue_present(q, &info) }) {
            Ok(suboptimal) => self.stale |= suboptimal,
            Err(vk::Result::ERROR_OUT_OF_DATE_KHR) => self.stale = true,
            Err(e) => return Err(device_error("presenting", e)),
        }
        if !screenshot {
            return Ok(None);
        }
        let texels: Vec<u32> = shot_buf.read_mapped(pixels as usize)?;
        let rgba = texels
            .iter()
            .flat_map(|t| {
                let [a, b, c, _] = t.to_le_bytes();
                // Undo the BGRA swap; sRGB swapchain values are the encoded display values.
                if sc.bgra {
                    [c, b, a, 255]
                } else {
                    [a, b, c, 255]
                }
            })
            .collect();
        Ok(Some((ext.width, ext.height, rgba)))
    }
}

/// Records the copy of the packed `texels` into swapchain image `target` and its transition to
/// the present layout; with `shot`, also the image's copy into that buffer (the screenshot).
fn copy_to_image(
    d: &ash::Device,
    cmd: vk::CommandBuffer,
    texels: &Buffer,
    target: vk::Image,
    ext: vk::Extent2D,
    shot: Option<&Buffer>,
) {
    let range =
        vk::ImageSubresourceRange::default().aspect_mask(vk::ImageAspectFlags::COLOR).level_count(1).layer_count(1);
    let to_dst = vk::ImageMemoryBarrier::default()
        .image(target)
        .subresource_range(range)
        .old_layout(vk::ImageLayout::UNDEFINED)
        .new_layout(vk::ImageLayout::TRANSFER_DST_OPTIMAL)
        .dst_access_mask(vk::AccessFlags::TRANSFER_WRITE);
    let region = vk::BufferImageCopy::default()
        .image_subresource(
            vk::ImageSubresourceLayers::default().aspect_mask(vk::ImageAspectFlags::COLOR).layer_count(1),
        )
        .image_extent(vk::Extent3D { width: ext.width, height: ext.height, depth: 1 });
    let last_layout =
        if shot.is_some() { vk::ImageLayout::TRANSFER_SRC_OPTIMAL } else { vk::ImageLayout::TRANSFER_DST_OPTIMAL };
    let to_present = vk::ImageMemoryBarrier::default()
        .image(target)
        .subresource_range(range)
        .old_layout(last_layout)
        .new_layout(vk::ImageLayout::PRESENT_SRC_KHR)
        .src_access_mask(if shot.is_some() { vk::AccessFlags::TRANSFER_READ } else { vk::AccessFlags::TRANSFER_WRITE });
    // An image layout transition between transfers.
    let transition = |b: vk::ImageMemoryBarrier| unsafe {
        d.cmd_pipeline_barrier(
            cmd,
            vk::PipelineStageFlags::TRANSFER,
            vk::PipelineStageFlags::TRANSFER,
            vk::DependencyFlags::empty(),
            &[],
            &[],
            &[b],
        )
    };
    transition(to_dst);
    unsafe {
        d.cmd_copy_buffer_to_image(cmd, texels.raw, target, vk::ImageLayout::TRANSFER_DST_OPTIMAL, &[region]);
        if let Some(shot) = shot {
            let to_src = vk::ImageMemoryBarrier::default()
                .image(target)
                .subresource_range(range)
                .old_layout(vk::ImageLayout::TRANSFER_DST_OPTIMAL)
                .new_layout(vk::ImageLayout::TRANSFER_SRC_OPTIMAL)
                .src_access_mask(vk::AccessFlags::TRANSFER_WRITE)
                .dst_access_mask(vk::AccessFlags::TRANSFER_READ);
            transition(to_src);
            d.cmd_copy_image_to_buffer(cmd, target, vk::ImageLayout::TRANSFER_SRC_OPTIMAL, shot.raw, &[region]);
        }
        let host = vk::MemoryBarrier::default()
            .src_access_mask(vk::AccessFlags::TRANSFER_WRITE)
            .dst_access_mask(vk::AccessFlags::HOST_READ);
        d.cmd_pipeline_barrier(
            cmd,
            vk::PipelineStageFlags::TRANSFER,
            vk::PipelineStageFlags::BOTTOM_OF_PIPE | vk::PipelineStageFlags::HOST,
            vk::DependencyFlags::empty(),
            &[host],
            &[],
            &[to_present],
        );
    }
}

impl Drop for Presenter {
    fn drop(&mut self) {
        unsafe {
            let _ = self.gpu.device.device_wait_idle();
        }
        if let Some(sc) = self.swapchain.take() {
            self.destroy(sc);
        }
        unsafe { self.gpu.device.destroy_semaphore(self.acquired, None) };
    }
}

fn device_error(what: &str, e: vk::Result) -> anyhow::Error {
    if e == vk::Result::ERROR_DEVICE_LOST {
        anyhow!("{what}: the GPU device was lost (driver reset or crash); restart the player")
    } else if e == vk::Result::ERROR_SURFACE_LOST_KHR {
        anyhow!("{what}: the window surface was lost")
    } else {
        anyhow!("{what}: {e}")
    }
}

/// 8-bit UNORM formats first (the image's values are display values); an _SRGB format is
/// accepted with the values decoded before its encoding write.
fn choose_format(formats: &[vk::SurfaceFormatKHR]) -> Result<(vk::SurfaceFormatKHR, bool, bool)> {
    let nonlinear = |f: &&vk::SurfaceFormatKHR| f.color_space == vk::ColorSpaceKHR::SRGB_NONLINEAR;
    for (want, bgra, srgb) in [
        (vk::Format::B8G8R8A8_UNORM, true, false),
        (vk::Format::R8G8B8A8_UNORM, false, false),
        (vk::Format::B8G8R8A8_SRGB, true, true),
        (vk::Format::R8G8B8A8_SRGB, false, true),
    ] {
        if let Some(f) = formats.iter().filter(nonlinear).find(|f| f.format == want) {
            return Ok((*f, bgra, srgb));
        }
    }
    bail!("the window surface offers no 8-bit RGBA/BGRA format (offered: {formats:?})")
}

/// Vsync off: immediate, else mailbox, else FIFO (always available). Vsync on: FIFO.
fn choose_present_mode(modes: &[vk::PresentModeKHR], vsync: bool) -> vk::PresentModeKHR {
    if !vsync {
        for m in [vk::PresentModeKHR::IMMEDIATE, vk::PresentModeKHR::MAILBOX] {
            if modes.contains(&m) {
                return m;
            }
        }
    }
    vk::PresentModeKHR::FIFO
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn present_mode_and_format_choice() {
        use vk::PresentModeKHR as M;
        assert_eq!(choose_present_mode(&[M::FIFO, M::MAILBOX, M::IMMEDIATE], false), M::IMMEDIATE);
        assert_eq!(choose_present_mode(&[M::FIFO, M::MAILBOX], false), M::MAILBOX);
        assert_eq!(choose_present_mode(&[M::FIFO, M::IMMEDIATE], true), M::FIFO);
        let f = |format| vk::SurfaceFormatKHR { format, color_space: vk::ColorSpaceKHR::SRGB_NONLINEAR };
        let (c, bgra, srgb) = choose_format(&[f(vk::Format::B8G8R8A8_SRGB), f(vk::Format::R8G8B8A8_UNORM)]).unwrap();
        assert_eq!((c.format, bgra, srgb), (vk::Format::R8G8B8A8_UNORM, false, false));
        assert!(choose_format(&[f(vk::Format::R16G16B16A16_SFLOAT)]).is_err());
    }
}
