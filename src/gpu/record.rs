//! Command recording and submission: a reusable command buffer, the recorder that binds,
//! dispatches (direct and indirect), copies and fills with the barriers between them, and GPU
//! timestamps per pass.
use std::sync::Arc;

use anyhow::{anyhow, bail, Result};
use ash::vk;

use crate::gpu::buffer::Buffer;
use crate::gpu::context::Gpu;
use crate::gpu::kernel::{Kernel, PipelineRef};
use gpu_allocator::MemoryLocation;

/// Named GPU timestamps: one before the first pass and one after every pass.
pub struct Timer {
    gpu: Arc<Gpu>,
    pool: vk::QueryPool,
    capacity: u32,
    names: Vec<String>,
}

impl Timer {
    pub fn new(gpu: &Arc<Gpu>, capacity: u32) -> Result<Option<Timer>> {
        if gpu.info.timestamp_period_ns.is_none() {
            return Ok(None);
        }
        let pool = unsafe {
            gpu.device.create_query_pool(
                &vk::QueryPoolCreateInfo::default().query_type(vk::QueryType::TIMESTAMP).query_count(capacity + 1),
                None,
            )?
        };
        Ok(Some(Timer { gpu: gpu.clone(), pool, capacity, names: Vec::new() }))
    }

    /// Milliseconds of every pass of the last submission, in record order. Passes with the same
    /// name are summed.
    pub fn results(&self) -> Result<Vec<(String, f64)>> {
        let n = self.names.len();
        if n == 0 {
            return Ok(Vec::new());
        }
        let mut ticks = vec![0u64; n + 1];
        unsafe {
            self.gpu.device.get_query_pool_results(
                self.pool,
                0,
                &mut ticks,
                vk::QueryResultFlags::TYPE_64 | vk::QueryResultFlags::WAIT,
            )?
        };
        let period = self.gpu.info.timestamp_period_ns.unwrap_or(1.0);
        let mut out: Vec<(String, f64)> = Vec::new();
        for (k, name) in self.names.iter().enumerate() {
            let ms = ticks[k + 1].saturating_sub(ticks[k]) as f64 * period * 1e-6;
            match out.iter_mut().find(|(n, _)| n == name) {
                Some(e) => e.1 += ms,
                None => out.push((name.clone(), ms)),
            }
        }
        Ok(out)
    }
}

impl Drop for Timer {
    fn drop(&mut self) {
        unsafe { self.gpu.device.destroy_query_pool(self.pool, None) };
    }
}

/// Records commands into one command buffer. Every dispatch and transfer is followed by a
/// global memory barrier (compute and transfer writes before compute, transfer and indirect
/// reads), since each pass here consumes the previous one's output.
pub struct Recorder<'a> {
    pub(crate) gpu: &'a Arc<Gpu>,
    pub(crate) cmd: vk::CommandBuffer,
    timer: Option<&'a mut Timer>,
}

impl Recorder<'_> {
    pub(crate) fn barrier(&mut self) {
        let mb = [vk::MemoryBarrier::default()
            .src_access_mask(vk::AccessFlags::SHADER_WRITE | vk::AccessFlags::TRANSFER_WRITE)
            .dst_access_mask(
                vk::AccessFlags::SHADER_READ
                    | vk::AccessFlags::SHADER_WRITE
                    | vk::AccessFlags::TRANSFER_READ
                    | vk::AccessFlags::TRANSFER_WRITE
                    | vk::AccessFlags::INDIRECT_COMMAND_READ
                    | vk::AccessFlags::UNIFORM_READ,
            )];
        unsafe {
            self.gpu.device.cmd_pipeline_barrier(
                self.cmd,
                vk::PipelineStageFlags::COMPUTE_SHADER | vk::PipelineStageFlags::TRANSFER,
                vk::PipelineStageFlags::COMPUTE_SHADER
                    | vk::PipelineStageFlags::TRANSFER
                    | vk::PipelineStageFlags::DRAW_INDIRECT,
                vk::DependencyFlags::empty(),
                &mb,
                &[],
                &[],
            )
        };
    }

    /// The command buffer being recorded, for commands this wrapper does not cover (image
    /// layout transitions and copies of the player).
    pub fn raw(&self) -> vk::CommandBuffer {
        self.cmd
    }

    /// Marks the end of a pass called `name` (timestamps, when the device has them).
    pub fn end_pass(&mut self, name: &str) -> Result<()> {
        if let Some(t) = self.timer.as_deref_mut() {
            let k = t.names.len() as u32;
            if k >= t.capacity {
                bail!("timer capacity {} exceeded", t.capacity);
            }
            unsafe {
                self.gpu.device.cmd_write_timestamp(self.cmd, vk::PipelineStageFlags::BOTTOM_OF_PIPE, t.pool, k + 1)
            };
            t.names.push(name.to_string());
        }
        Ok(())
    }

    pub fn copy(&mut self, src: &Buffer, dst: &Buffer, bytes: u64) {
        self.copy_region(src, 0, dst, 0, bytes);
    }

    /// Copies `bytes` from `src` at byte `src_offset` to `dst` at byte `dst_offset`.
    pub fn copy_region(&mut self, src: &Buffer, src_offset: u64, dst: &Buffer, dst_offset: u64, bytes: u64) {
        let region = [vk::BufferCopy::default().src_offset(src_offset).dst_offset(dst_offset).size(bytes)];
        unsafe { self.gpu.device.cmd_copy_buffer(self.cmd, src.raw, dst.raw, &region) };
        self.barrier();
    }

    /// Fills the whole buffer with a 32-bit value.
    pub fn fill(&mut self, dst: &Buffer, value: u32) {
        unsafe { self.gpu.device.cmd_fill_buffer(self.cmd, dst.raw, 0, vk::WHOLE_SIZE, value) };
        self.barrier();
    }

    /// Writes up to 64 KiB of data at the start of `dst` inside the command buffer.
    pub fn update<T: bytemuck::Pod>(&mut self, dst: &Buffer, data: &[T]) {
        unsafe { self.gpu.device.cmd_update_buffer(self.cmd, dst.raw, 0, bytemuck::cast_slice(data)) };
        self.barrier();
    }

    fn bind<P: bytemuck::Pod>(&mut self, k: &Kernel, binds: &[(&str, &Buffer)], push: &P) -> Result<()> {
        self.bind_pipeline(&k.pipeline_ref(), binds, push)
    }

    /// Binds a pipeline, its buffers by GLSL name (push descriptors) and its push constants.
    pub(crate) fn bind_pipeline<P: bytemuck::Pod>(
        &mut self,
        k: &PipelineRef,
        binds: &[(&str, &Buffer)],
        push: &P,
    ) -> Result<()> {
        if binds.len() != k.bindings.len() {
            let want: Vec<&String> = k.bindings.keys().collect();
            let got: Vec<&str> = binds.iter().map(|b| b.0).collect();
            bail!("kernel {}: expects buffers {want:?}, got {got:?}", k.name);
        }
        let mut infos = Vec::with_capacity(binds.len());
        let mut views = Vec::with_capacity(binds.len());
        let mut meta = Vec::with_capacity(binds.len());
        for (name, buf) in binds {
            let b = *k.bindings.get(*name).ok_or_else(|| anyhow!("kernel {}: no buffer named '{name}'", k.name))?;
            let (binding, ty) = (b.binding, b.ty);
            if ty == vk::DescriptorType::STORAGE_BUFFER && buf.size > self.gpu.info.max_storage_buffer_range {
                bail!(
                    "buffer '{}' ({} bytes) exceeds the device's maxStorageBufferRange ({} bytes)",
                    buf.name,
                    buf.size,
                    self.gpu.info.max_storage_buffer_range
                );
            }
            infos.push([vk::DescriptorBufferInfo::default().buffer(buf.raw).offset(0).range(vk::WHOLE_SIZE)]);
            let view = if ty == vk::DescriptorType::UNIFORM_TEXEL_BUFFER {
                buf.texel_view(b.format)?
            } else {
                vk::BufferView::null()
            };
            views.push([view]);
            meta.push((binding, ty));
        }
        let writes: Vec<vk::WriteDescriptorSet> = infos
            .iter()
            .zip(&views)
            .zip(&meta)
            .map(|((info, view), &(binding, ty))| {
                let w = vk::WriteDescriptorSet::default().dst_binding(binding).descriptor_type(ty);
                if ty == vk::DescriptorType::UNIFORM_TEXEL_BUFFER {
                    w.texel_buffer_view(view)
                } else {
                    w.buffer_info(info)
                }
            })
            .collect();
        let bytes: &[u8] = bytemuck::bytes_of(push);
        if bytes.len() as u32 != k.push_size && !(k.push_size == 0 && bytes.is_empty()) {
            bail!("kernel {}: push constants are {} bytes, given {}", k.name, k.push_size, bytes.len());
        }
        unsafe {
            let d = &self.gpu.device;
            d.cmd_bind_pipeline(self.cmd, k.point, k.pipeline);
            self.gpu.push_descriptor.cmd_push_descriptor_set(self.cmd, k.point, k.layout, 0, &writes);
            if k.push_size > 0 {
                d.cmd_push_constants(self.cmd, k.layout, k.stages, 0, bytes);
            }
        }
        Ok(())
    }

    /// Dispatches `groups` workgroups.
    pub fn dispatch<P: bytemuck::Pod>(
        &mut self,
        k: &Kernel,
        binds: &[(&str, &Buffer)],
        push: &P,
        groups: [u32; 3],
    ) -> Result<()> {
        self.bind(k, binds, push)?;
        unsafe { self.gpu.device.cmd_dispatch(self.cmd, groups[0], groups[1], groups[2]) };
        self.barrier();
        Ok(())
    }

    /// Dispatches with workgroup counts read by the GPU from `args` at byte `offset`.
    pub fn dispatch_indirect<P: bytemuck::Pod>(
        &mut self,
        k: &Kernel,
        binds: &[(&str, &Buffer)],
        push: &P,
        args: &Buffer,
        offset: u64,
    ) -> Result<()> {
        self.bind(k, binds, push)?;
        unsafe { self.gpu.device.cmd_dispatch_indirect(self.cmd, args.raw, offset) };
        self.barrier();
        Ok(())
    }
}

/// A primary command buffer with its own pool and fence, recorded once and submitted any
/// number of times. One pool each keeps recording on different threads independent.
pub struct CommandBuffer {
    gpu: Arc<Gpu>,
    pool: vk::CommandPool,
    cmd: vk::CommandBuffer,
    fence: vk::Fence,
    in_flight: std::cell::Cell<bool>,
}

impl CommandBuffer {
    pub fn new(gpu: &Arc<Gpu>) -> Result<CommandBuffer> {
        let pool = unsafe {
            gpu.device.create_command_pool(
                &vk::CommandPoolCreateInfo::default()
                    .queue_family_index(gpu.queue_family)
                    .flags(vk::CommandPoolCreateFlags::RESET_COMMAND_BUFFER),
                None,
            )?
        };
        let cmd = unsafe {
            gpu.device.allocate_command_buffers(
                &vk::CommandBufferAllocateInfo::default().command_pool(pool).command_buffer_count(1),
            )?[0]
        };
        let fence = unsafe { gpu.device.create_fence(&vk::FenceCreateInfo::default(), None)? };
        Ok(CommandBuffer { gpu: gpu.clone(), pool, cmd, fence, in_flight: std::cell::Cell::new(false) })
    }

    /// Records the command buffer (replacing earlier contents).
    pub fn record(&self, f: impl FnOnce(&mut Recorder) -> Result<()>) -> Result<()> {
        self.record_timed(None, f)
    }

    /// Records with timestamps into `timer` (reset at the start).
    pub fn record_timed(&self, timer: Option<&mut Timer>, f: impl FnOnce(&mut Recorder) -> Result<()>) -> Result<()> {
        let d = &self.gpu.device;
        unsafe {
            d.reset_command_buffer(self.cmd, vk::CommandBufferResetFlags::empty())?;
            d.begin_command_buffer(self.cmd, &vk::CommandBufferBeginInfo::default())?;
        }
        let mut timer = timer;
        if let Some(t) = timer.as_deref_mut() {
            t.names.clear();
            unsafe {
                d.cmd_reset_query_pool(self.cmd, t.pool, 0, t.capacity + 1);
                d.cmd_write_timestamp(self.cmd, vk::PipelineStageFlags::TOP_OF_PIPE, t.pool, 0);
            }
        }
        let mut rec = Recorder { gpu: &self.gpu, cmd: self.cmd, timer };
        let r = f(&mut rec);
        unsafe { d.end_command_buffer(self.cmd)? };
        r
    }

    pub fn submit_and_wait(&self) -> Result<()> {
        self.submit_and_wait_sync(&[], &[])
    }

    /// Submits after `waits` (semaphore, stage) are signalled, signals `signals` when done,
    /// and waits.
    pub fn submit_and_wait_sync(
        &self,
        waits: &[(vk::Semaphore, vk::PipelineStageFlags)],
        signals: &[vk::Semaphore],
    ) -> Result<()> {
        let d = &self.gpu.device;
        let cmds = [self.cmd];
        let wait_sems: Vec<vk::Semaphore> = waits.iter().map(|w| w.0).collect();
        let wait_stages: Vec<vk::PipelineStageFlags> = waits.iter().map(|w| w.1).collect();
        let submit = [vk::SubmitInfo::default()
            .command_buffers(&cmds)
            .wait_semaphores(&wait_sems)
            .wait_dst_stage_mask(&wait_stages)
            .signal_semaphores(signals)];
        unsafe {
            d.reset_fences(&[self.fence])?;
            {
                let _q = self.gpu.queue_lock.lock().unwrap();
                d.queue_submit(self.gpu.queue, &submit, self.fence)?;
            }
            self.in_flight.set(true);
            d.wait_for_fences(&[self.fence], true, u64::MAX)
                .map_err(|e| anyhow!("waiting for the GPU failed ({e}); the device may be lost"))?;
            self.in_flight.set(false);
        }
        Ok(())
    }
}

impl Drop for CommandBuffer {
    fn drop(&mut self) {
        unsafe {
            if self.in_flight.get() {
                let _ = self.gpu.device.wait_for_fences(&[self.fence], true, u64::MAX);
            }
            self.gpu.device.destroy_fence(self.fence, None);
            self.gpu.device.free_command_buffers(self.pool, &[self.cmd]);
            self.gpu.device.destroy_command_pool(self.pool, None);
        }
    }
}

/// Buffers that need commands: poisoned storage, uploads, writes and read-backs.
impl Gpu {
    /// A device-local storage buffer (filled with 0xffffffff with [`GpuOptions::poison`](crate::gpu::GpuOptions::poison)).
    pub fn storage(self: &Arc<Self>, name: &str, size: u64) -> Result<Buffer> {
        let b = self.buffer(
            name,
            size,
            vk::BufferUsageFlags::STORAGE_BUFFER | vk::BufferUsageFlags::INDIRECT_BUFFER,
            MemoryLocation::GpuOnly,
        )?;
        if self.poison {
            self.submit_and_wait(|rec| {
                rec.fill(&b, 0xffff_ffff);
                Ok(())
            })?;
        }
        Ok(b)
    }

    /// A device-local storage buffer holding `data` (uploaded through a staging buffer).
    pub fn upload<T: bytemuck::Pod>(self: &Arc<Self>, name: &str, data: &[T]) -> Result<Buffer> {
        let buf = self.storage(name, std::mem::size_of_val(data) as u64)?;
        self.write(&buf, data)?;
        Ok(buf)
    }

    /// Overwrites the start of `dst` with `data` through a staging buffer and waits.
    pub fn write<T: bytemuck::Pod>(self: &Arc<Self>, dst: &Buffer, data: &[T]) -> Result<()> {
        self.write_at(dst, 0, data)
    }

    /// Overwrites `dst` from byte `offset` on with `data` through a staging buffer and waits.
    pub fn write_at<T: bytemuck::Pod>(self: &Arc<Self>, dst: &Buffer, offset: u64, data: &[T]) -> Result<()> {
        let bytes: &[u8] = bytemuck::cast_slice(data);
        if bytes.is_empty() {
            return Ok(());
        }
        if offset.checked_add(bytes.len() as u64).is_none_or(|end| end > dst.size) {
            bail!("writing {} bytes at {offset} into buffer '{}' of {} bytes", bytes.len(), dst.name, dst.size);
        }
        let mut staging =
            self.buffer("staging-up", bytes.len() as u64, vk::BufferUsageFlags::empty(), MemoryLocation::CpuToGpu)?;
        staging.mapped_mut()?[..bytes.len()].copy_from_slice(bytes);
        self.submit_and_wait(|rec| {
            rec.copy_region(&staging, 0, dst, offset, bytes.len() as u64);
            Ok(())
        })
    }

    /// Reads the first `count` elements of `src` back to the host (waits for the GPU).
    pub fn read<T: bytemuck::Pod>(self: &Arc<Self>, src: &Buffer, count: usize) -> Result<Vec<T>> {
        self.read_at(src, 0, count)
    }

    /// Reads `count` elements of `src` from byte `offset` on back to the host (waits for the GPU).
    pub fn read_at<T: bytemuck::Pod>(self: &Arc<Self>, src: &Buffer, offset: u64, count: usize) -> Result<Vec<T>> {
        let bytes = (count * std::mem::size_of::<T>()) as u64;
        if offset.checked_add(bytes).is_none_or(|end| end > src.size) {
            bail!("reading {bytes} bytes at {offset} from buffer '{}' of {} bytes", src.name, src.size);
        }
        if count == 0 {
            return Ok(Vec::new());
        }
        let staging = self.buffer("staging-down", bytes, vk::BufferUsageFlags::empty(), MemoryLocation::GpuToCpu)?;
        self.submit_and_wait(|rec| {
            rec.copy_region(src, offset, &staging, 0, bytes);
            Ok(())
        })?;
        let mapped = staging.mapped()?;
        Ok(bytemuck::pod_collect_to_vec(&mapped[..bytes as usize]))
    }

    /// Records commands with `f`, submits them and waits for completion.
    pub fn submit_and_wait(self: &Arc<Self>, f: impl FnOnce(&mut Recorder) -> Result<()>) -> Result<()> {
        let cmd = CommandBuffer::new(self)?;
        cmd.record(|rec| f(rec))?;
        cmd.submit_and_wait()
    }
}
