//! The draw path's Vulkan objects: a render pass with one RGBA32F colour attachment, two
//! graphics pipelines whose descriptor layouts are reflected like the kernels' (buffers bound by
//! GLSL name), the render target, and the recording of a frame's draws. What is drawn is
//! `render::raster::quads`' business; this module only knows pipelines, targets and commands.
//!
//! Blending is front to back with the transmittance in the attachment's alpha (cleared to
//! (0, 0, 0, 1)): colour += dst.a · src.rgb (src.rgb premultiplied), dst.a *= 1 − src.a. The
//! background pipeline writes rgb only, so the target ends as blend.comp's `out_image`:
//! rgb = C + T · background, a = T.
use std::collections::BTreeMap;
use std::ffi::CString;
use std::sync::Arc;

use anyhow::{anyhow, bail, Result};
use ash::vk;
use gpu_allocator::vulkan::{Allocation, AllocationCreateDesc, AllocationScheme};
use gpu_allocator::MemoryLocation;

use crate::gpu::context::TARGET_FORMAT;
use crate::gpu::kernel::{create_layouts, reflect, Binding, PipelineRef, Reflected};
use crate::gpu::{Buffer, Gpu, Recorder};
use crate::shared::spirv;

/// One graphics pipeline (vertex + fragment shader, no vertex buffers) of the render pass.
struct DrawPipeline {
    name: String,
    pipeline: vk::Pipeline,
    layout: vk::PipelineLayout,
    set_layout: vk::DescriptorSetLayout,
    bindings: BTreeMap<String, Binding>,
    push_size: u32,
}

impl DrawPipeline {
    fn new(
        gpu: &Arc<Gpu>,
        name: &str,
        (vert, frag): (&[u8], &[u8]),
        render_pass: vk::RenderPass,
        topology: vk::PrimitiveTopology,
        write: vk::ColorComponentFlags,
    ) -> Result<DrawPipeline> {
        let stages = vk::ShaderStageFlags::VERTEX | vk::ShaderStageFlags::FRAGMENT;
        let Reflected { bindings, layout_bindings, push_size } = reflect(name, &[vert, frag], stages)?;
        let d = &gpu.device;
        let (set_layout, layout) = create_layouts(gpu, &layout_bindings, push_size, stages)?;
        unsafe {
            let module = |spv: &[u8]| -> Result<vk::ShaderModule> {
                let words = ash::util::read_spv(&mut std::io::Cursor::new(spv))?;
                Ok(d.create_shader_module(&vk::ShaderModuleCreateInfo::default().code(&words), None)?)
            };
            let (vm, fm) = (module(vert)?, module(frag)?);
            let entry = CString::new("main").unwrap();
            let shader_stages = [
                vk::PipelineShaderStageCreateInfo::default()
                    .stage(vk::ShaderStageFlags::VERTEX)
                    .module(vm)
                    .name(&entry),
                vk::PipelineShaderStageCreateInfo::default()
                    .stage(vk::ShaderStageFlags::FRAGMENT)
                    .module(fm)
                    .name(&entry),
            ];
            let vertex_input = vk::PipelineVertexInputStateCreateInfo::default();
            let assembly = vk::PipelineInputAssemblyStateCreateInfo::default().topology(topology);
            let viewport = vk::PipelineViewportStateCreateInfo::default().viewport_count(1).scissor_count(1);
            let raster = vk::PipelineRasterizationStateCreateInfo::default()
                .polygon_mode(vk::PolygonMode::FILL)
                .cull_mode(vk::CullModeFlags::NONE)
                .front_face(vk::FrontFace::COUNTER_CLOCKWISE)
                .line_width(1.0);
            let multisample =
                vk::PipelineMultisampleStateCreateInfo::default().rasterization_samples(vk::SampleCountFlags::TYPE_1);
            let blend = [vk::PipelineColorBlendAttachmentState::default()
                .blend_enable(true)
                .src_color_blend_factor(vk::BlendFactor::DST_ALPHA)
                .dst_color_blend_factor(vk::BlendFactor::ONE)
                .color_blend_op(vk::BlendOp::ADD)
                .src_alpha_blend_factor(vk::BlendFactor::ZERO)
                .dst_alpha_blend_factor(vk::BlendFactor::ONE_MINUS_SRC_ALPHA)
                .alpha_blend_op(vk::BlendOp::ADD)
                .color_write_mask(write)];
            let blend_state = vk::PipelineColorBlendStateCreateInfo::default().attachments(&blend);
            let dynamic = [vk::DynamicState::VIEWPORT, vk::DynamicState::SCISSOR];
            let dynamic_state = vk::PipelineDynamicStateCreateInfo::default().dynamic_states(&dynamic);
            let pci = [vk::GraphicsPipelineCreateInfo::default()
                .stages(&shader_stages)
                .vertex_input_state(&vertex_input)
                .input_assembly_state(&assembly)
                .viewport_state(&viewport)
                .rasterization_state(&raster)
                .multisample_state(&multisample)
                .color_blend_state(&blend_state)
                .dynamic_state(&dynamic_state)
                .layout(layout)
                .render_pass(render_pass)
                .subpass(0)];
            let pipeline = d.create_graphics_pipelines(vk::PipelineCache::null(), &pci, None);
            d.destroy_shader_module(vm, None);
            d.destroy_shader_module(fm, None);
            let pipeline = pipeline.map_err(|(_, e)| anyhow!("pipeline {name}: creation failed: {e}"))?[0];
            Ok(DrawPipeline { name: name.to_string(), pipeline, layout, set_layout, bindings, push_size })
        }
    }

    fn pipeline_ref(&self) -> PipelineRef<'_> {
        PipelineRef {
            name: &self.name,
            pipeline: self.pipeline,
            layout: self.layout,
            bindings: &self.bindings,
            push_size: self.push_size,
            point: vk::PipelineBindPoint::GRAPHICS,
            stages: vk::ShaderStageFlags::VERTEX | vk::ShaderStageFlags::FRAGMENT,
        }
    }

    fn destroy(&self, d: &ash::Device) {
        unsafe {
            d.destroy_pipeline(self.pipeline, None);
            d.destroy_pipeline_layout(self.layout, None);
            d.destroy_descriptor_set_layout(self.set_layout, None);
        }
    }
}

/// The render pass and the two pipelines of the splat draw: `splat_quads` (instanced triangle
/// strips, a quad per splat) and `splat_background` (one triangle over the image, rgb only).
pub struct SplatDraw {
    gpu: Arc<Gpu>,
    render_pass: vk::RenderPass,
    splats: DrawPipeline,
    background: DrawPipeline,
}

impl SplatDraw {
    pub fn new(gpu: &Arc<Gpu>) -> Result<SplatDraw> {
        if !gpu.info.draws {
            bail!(
                "device '{}' cannot draw splats (its queue has no graphics, or RGBA32F attachments do not blend); use --forward compute",
                gpu.info.name
            );
        }
        let d = &gpu.device;
        let attachment = [vk::AttachmentDescription::default()
            .format(TARGET_FORMAT)
            .samples(vk::SampleCountFlags::TYPE_1)
            .load_op(vk::AttachmentLoadOp::CLEAR)
            .store_op(vk::AttachmentStoreOp::STORE)
            .stencil_load_op(vk::AttachmentLoadOp::DONT_CARE)
            .stencil_store_op(vk::AttachmentStoreOp::DONT_CARE)
            .initial_layout(vk::ImageLayout::UNDEFINED)
            .final_layout(vk::ImageLayout::TRANSFER_SRC_OPTIMAL)];
        let colour =
            [vk::AttachmentReference::default().attachment(0).layout(vk::ImageLayout::COLOR_ATTACHMENT_OPTIMAL)];
        let subpass = [vk::SubpassDescription::default()
            .pipeline_bind_point(vk::PipelineBindPoint::GRAPHICS)
            .color_attachments(&colour)];
        let blend_access = vk::AccessFlags::COLOR_ATTACHMENT_READ | vk::AccessFlags::COLOR_ATTACHMENT_WRITE;
        let deps = [
            // The last frame's copy out of the target ends before this frame clears it.
            vk::SubpassDependency::default()
                .src_subpass(vk::SUBPASS_EXTERNAL)
                .dst_subpass(0)
                .src_stage_mask(vk::PipelineStageFlags::TRANSFER)
                .dst_stage_mask(vk::PipelineStageFlags::COLOR_ATTACHMENT_OUTPUT)
                .src_access_mask(vk::AccessFlags::empty())
                .dst_access_mask(blend_access),
            // The blended image is complete before it is copied out.
            vk::SubpassDependency::default()
                .src_subpass(0)
                .dst_subpass(vk::SUBPASS_EXTERNAL)
                .src_stage_mask(vk::PipelineStageFlags::COLOR_ATTACHMENT_OUTPUT)
                .dst_stage_mask(vk::PipelineStageFlags::TRANSFER)
                .src_access_mask(vk::AccessFlags::COLOR_ATTACHMENT_WRITE)
                .dst_access_mask(vk::AccessFlags::TRANSFER_READ),
        ];
        let render_pass = unsafe {
            d.create_render_pass(
                &vk::RenderPassCreateInfo::default().attachments(&attachment).subpasses(&subpass).dependencies(&deps),
                None,
            )?
        };
        let splats = DrawPipeline::new(
            gpu,
            "splat_quads",
            (spirv::SPLAT_QUADS_VERT, spirv::SPLAT_QUADS_FRAG),
            render_pass,
            vk::PrimitiveTopology::TRIANGLE_STRIP,
            vk::ColorComponentFlags::RGBA,
        );
        let background = DrawPipeline::new(
            gpu,
            "splat_background",
            (spirv::SPLAT_BACKGROUND_VERT, spirv::SPLAT_BACKGROUND_FRAG),
            render_pass,
            vk::PrimitiveTopology::TRIANGLE_LIST,
            vk::ColorComponentFlags::R | vk::ColorComponentFlags::G | vk::ColorComponentFlags::B,
        );
        match (splats, background) {
            (Ok(splats), Ok(background)) => Ok(SplatDraw { gpu: gpu.clone(), render_pass, splats, background }),
            (s, b) => {
                for p in [s.as_ref().ok(), b.as_ref().ok()].into_iter().flatten() {
                    p.destroy(d);
                }
                unsafe { d.destroy_render_pass(render_pass, None) };
                Err(s.err().or(b.err()).unwrap())
            }
        }
    }
}

impl Drop for SplatDraw {
    fn drop(&mut self) {
        let d = &self.gpu.device;
        self.splats.destroy(d);
        self.background.destroy(d);
        unsafe { d.destroy_render_pass(self.render_pass, None) };
    }
}

/// The colour attachment of one image size, its view and framebuffer.
pub struct RenderTarget {
    gpu: Arc<Gpu>,
    image: vk::Image,
    view: vk::ImageView,
    framebuffer: vk::Framebuffer,
    alloc: Option<Allocation>,
    pub width: u32,
    pub height: u32,
}

impl RenderTarget {
    pub fn new(gpu: &Arc<Gpu>, draw: &SplatDraw, width: u32, height: u32) -> Result<RenderTarget> {
        let d = &gpu.device;
        let image = unsafe {
            d.create_image(
                &vk::ImageCreateInfo::default()
                    .image_type(vk::ImageType::TYPE_2D)
                    .format(TARGET_FORMAT)
                    .extent(vk::Extent3D { width, height, depth: 1 })
                    .mip_levels(1)
                    .array_layers(1)
                    .samples(vk::SampleCountFlags::TYPE_1)
                    .tiling(vk::ImageTiling::OPTIMAL)
                    .usage(vk::ImageUsageFlags::COLOR_ATTACHMENT | vk::ImageUsageFlags::TRANSFER_SRC)
                    .initial_layout(vk::ImageLayout::UNDEFINED),
                None,
            )?
        };
        let mut t = RenderTarget {
            gpu: gpu.clone(),
            image,
            view: vk::ImageView::null(),
            framebuffer: vk::Framebuffer::null(),
            alloc: None,
            width,
            height,
        };
        let requirements = unsafe { d.get_image_memory_requirements(image) };
        let alloc = gpu
            .allocator
            .lock()
            .unwrap()
            .allocate(&AllocationCreateDesc {
                name: "splat-target",
                requirements,
                location: MemoryLocation::GpuOnly,
                linear: false,
                allocation_scheme: AllocationScheme::GpuAllocatorManaged,
            })
            .map_err(|e| anyhow!("cannot allocate the {width}x{height} draw target: {e}"))?;
        unsafe { d.bind_image_memory(image, alloc.memory(), alloc.offset())? };
        t.alloc = Some(alloc);
        t.view = unsafe {
            d.create_image_view(
                &vk::ImageViewCreateInfo::default()
                    .image(image)
                    .view_type(vk::ImageViewType::TYPE_2D)
                    .format(TARGET_FORMAT)
                    .subresource_range(colour_range()),
                None,
            )?
        };
        let views = [t.view];
        t.framebuffer = unsafe {
            d.create_framebuffer(
                &vk::FramebufferCreateInfo::default()
                    .render_pass(draw.render_pass)
                    .attachments(&views)
                    .width(width)
                    .height(height)
                    .layers(1),
                None,
            )?
        };
        Ok(t)
    }

    /// Device bytes of the attachment.
    pub fn bytes(&self) -> u64 {
        self.alloc.as_ref().map_or(0, |a| a.size())
    }
}

fn colour_range() -> vk::ImageSubresourceRange {
    vk::ImageSubresourceRange::default().aspect_mask(vk::ImageAspectFlags::COLOR).level_count(1).layer_count(1)
}

impl Drop for RenderTarget {
    fn drop(&mut self) {
        let d = &self.gpu.device;
        unsafe {
            d.destroy_framebuffer(self.framebuffer, None);
            d.destroy_image_view(self.view, None);
            d.destroy_image(self.image, None);
        }
        if let Some(a) = self.alloc.take() {
            let _ = self.gpu.allocator.lock().unwrap().free(a);
        }
    }
}

/// One frame's draws (see [`Recorder::draw_splats`]).
pub struct SplatDrawCall<'a> {
    /// Buffers of `splat_quads` by GLSL name.
    pub splats: &'a [(&'a str, &'a Buffer)],
    /// A VkDrawIndirectCommand at byte `args_offset` of `args`.
    pub args: &'a Buffer,
    pub args_offset: u64,
    /// Buffers of `splat_background` by GLSL name.
    pub background: &'a [(&'a str, &'a Buffer)],
    /// Receives the image, row-major RGBA32F texels (width × height × 16 bytes).
    pub out: &'a Buffer,
}

impl Recorder<'_> {
    /// Draws the splats, then the background, into `target` and copies the image into
    /// `call.out`. Compute and transfer writes before it are visible to the draws.
    pub fn draw_splats(&mut self, draw: &SplatDraw, target: &RenderTarget, call: &SplatDrawCall) -> Result<()> {
        let d = &self.gpu.device;
        let (w, h) = (target.width, target.height);
        if call.out.size < w as u64 * h as u64 * 16 {
            bail!("buffer '{}' cannot hold a {w}x{h} RGBA32F image", call.out.name);
        }
        let mb = [vk::MemoryBarrier::default()
            .src_access_mask(vk::AccessFlags::SHADER_WRITE | vk::AccessFlags::TRANSFER_WRITE)
            .dst_access_mask(vk::AccessFlags::INDIRECT_COMMAND_READ | vk::AccessFlags::SHADER_READ)];
        let extent = vk::Extent2D { width: w, height: h };
        let clear = [vk::ClearValue { color: vk::ClearColorValue { float32: [0.0, 0.0, 0.0, 1.0] } }];
        unsafe {
            d.cmd_pipeline_barrier(
                self.cmd,
                vk::PipelineStageFlags::COMPUTE_SHADER | vk::PipelineStageFlags::TRANSFER,
                vk::PipelineStageFlags::DRAW_INDIRECT
                    | vk::PipelineStageFlags::VERTEX_SHADER
                    | vk::PipelineStageFlags::FRAGMENT_SHADER,
                vk::DependencyFlags::empty(),
                &mb,
                &[],
                &[],
            );
            d.cmd_begin_render_pass(
                self.cmd,
                &vk::RenderPassBeginInfo::default()
                    .render_pass(draw.render_pass)
                    .framebuffer(target.framebuffer)
                    .render_area(vk::Rect2D { offset: vk::Offset2D::default(), extent })
                    .clear_values(&clear),
                vk::SubpassContents::INLINE,
            );
            let viewport = [vk::Viewport::default().width(w as f32).height(h as f32).max_depth(1.0)];
            d.cmd_set_viewport(self.cmd, 0, &viewport);
            d.cmd_set_scissor(self.cmd, 0, &[vk::Rect2D { offset: vk::Offset2D::default(), extent }]);
        }
        self.bind_pipeline(&draw.splats.pipeline_ref(), call.splats, &())?;
        unsafe { d.cmd_draw_indirect(self.cmd, call.args.raw, call.args_offset, 1, 16) };
        self.bind_pipeline(&draw.background.pipeline_ref(), call.background, &())?;
        unsafe {
            d.cmd_draw(self.cmd, 3, 1, 0, 0);
            d.cmd_end_render_pass(self.cmd);
            let region = [vk::BufferImageCopy::default()
                .image_subresource(
                    vk::ImageSubresourceLayers::default().aspect_mask(vk::ImageAspectFlags::COLOR).layer_count(1),
                )
                .image_extent(vk::Extent3D { width: w, height: h, depth: 1 })];
            d.cmd_copy_image_to_buffer(
                self.cmd,
                target.image,
                vk::ImageLayout::TRANSFER_SRC_OPTIMAL,
                call.out.raw,
                &region,
            );
        }
        self.barrier();
        Ok(())
    }
}
