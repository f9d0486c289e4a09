//! Vulkan context on `ash` + `gpu-allocator`: device choice, validation layers, buffers,
//! compute kernels with reflected descriptor layouts, command recording and GPU timestamps.
//!
//! Device choice: a discrete GPU over an integrated one over a virtual one over a CPU device
//! (lavapipe). `INSTGS_DEVICE` or `--device NAME|INDEX` overrides (a name matches by
//! case-insensitive substring). `INSTGS_VALIDATION=1` enables `VK_LAYER_KHRONOS_validation`
//! with synchronization validation; its warnings and errors are collected (see
//! [`Gpu::take_validation_messages`]) and echoed to stderr. `INSTGS_POISON=1` fills every new
//! device-local storage buffer with 0xffffffff (a NaN as f32, the largest u32), so a run that
//! reads memory nothing wrote differs from one without it (tests compare the two).

pub mod kernels;
use std::collections::BTreeMap;
use std::ffi::{c_void, CStr, CString};
use std::mem::ManuallyDrop;
use std::sync::{Arc, Mutex};

use anyhow::{anyhow, bail, Context, Result};
use ash::vk;
use gpu_allocator::vulkan::{Allocation, AllocationCreateDesc, AllocationScheme, Allocator, AllocatorCreateDesc};
use gpu_allocator::MemoryLocation;

/// How to pick and set up the device.
#[derive(Clone, Debug, Default)]
pub struct GpuOptions {
    /// Device index (as listed by the Vulkan loader) or a case-insensitive name substring.
    pub device: Option<String>,
    /// Enable the Khronos validation layer with synchronization validation.
    pub validation: bool,
    /// Echo validation messages to stderr as they arrive.
    pub echo_messages: bool,
    /// A window to present to: enables the surface and swapchain extensions, creates its
    /// surface ([`Gpu::surface`]) and requires a queue family that can present to it.
    pub window: Option<(raw_window_handle::RawDisplayHandle, raw_window_handle::RawWindowHandle)>,
    /// Fill every new device-local storage buffer with 0xffffffff (see the module docs).
    pub poison: bool,
}

impl GpuOptions {
    /// Options from the environment: `INSTGS_DEVICE`, `INSTGS_VALIDATION=1`, `INSTGS_POISON=1`.
    /// An explicit `device` wins over the variable.
    pub fn from_env(device: Option<String>) -> Self {
        let flag = |name: &str| std::env::var(name).is_ok_and(|v| v != "0" && !v.is_empty());
        let validation = flag("INSTGS_VALIDATION");
        GpuOptions {
            poison: flag("INSTGS_POISON"),
            device: device.or_else(|| std::env::var("INSTGS_DEVICE").ok().filter(|s| !s.is_empty())),
            validation,
            echo_messages: true,
            window: None,
        }
    }
}

/// Facts about the chosen device that the kernels and the host code depend on.
#[derive(Clone, Debug)]
pub struct DeviceInfo {
    pub name: String,
    pub kind: &'static str,
    /// Subgroup size the device reports (lavapipe: 8).
    pub subgroup_size: u32,
    /// Smallest subgroup size the device may use (bounds shared arrays per subgroup).
    pub min_subgroup_size: u32,
    pub max_storage_buffer_range: u64,
    /// Nanoseconds per timestamp tick; `None` when the compute queue has no timestamps.
    pub timestamp_period_ns: Option<f64>,
    /// `shaderBufferFloat32AtomicAdd` (VK_EXT_shader_atomic_float) is available and enabled;
    /// without it the gradient kernels use their compare-and-swap variants.
    pub float_atomics: bool,
}

struct Messages(Mutex<Vec<String>>, bool);

/// A window surface and the swapchain entry points (see [`GpuOptions::window`]).
pub struct Surface {
    pub loader: ash::khr::surface::Instance,
    pub raw: vk::SurfaceKHR,
    pub swapchain: ash::khr::swapchain::Device,
}

/// The Vulkan instance, device, queue and allocator. Shared as `Arc<Gpu>`.
pub struct Gpu {
    _entry: ash::Entry,
    instance: ash::Instance,
    debug: Option<(ash::ext::debug_utils::Instance, vk::DebugUtilsMessengerEXT)>,
    messages: Box<Messages>,
    pub device: ash::Device,
    queue: vk::Queue,
    pub push_descriptor: ash::khr::push_descriptor::Device,
    allocator: ManuallyDrop<Mutex<Allocator>>,
    /// Submissions to `queue` must be externally synchronised.
    queue_lock: Mutex<()>,
    queue_family: u32,
    pub physical: vk::PhysicalDevice,
    pub surface: Option<Surface>,
    pub info: DeviceInfo,
    poison: bool,
}

unsafe extern "system" fn debug_callback(
    severity: vk::DebugUtilsMessageSeverityFlagsEXT,
    _types: vk::DebugUtilsMessageTypeFlagsEXT,
    data: *const vk::DebugUtilsMessengerCallbackDataEXT<'_>,
    user: *mut c_void,
) -> vk::Bool32 {
    let msgs = &*(user as *const Messages);
    let text = if data.is_null() || (*data).p_message.is_null() {
        "(no message)".to_string()
    } else {
        CStr::from_ptr((*data).p_message).to_string_lossy().into_owned()
    };
    let line = format!("{severity:?}: {text}");
    if msgs.1 {
        eprintln!("vulkan validation: {line}");
    }
    if let Ok(mut v) = msgs.0.lock() {
        v.push(line);
    }
    vk::FALSE
}

fn kind_rank(t: vk::PhysicalDeviceType) -> (u32, &'static str) {
    match t {
        vk::PhysicalDeviceType::DISCRETE_GPU => (0, "discrete GPU"),
        vk::PhysicalDeviceType::INTEGRATED_GPU => (1, "integrated GPU"),
        vk::PhysicalDeviceType::VIRTUAL_GPU => (2, "virtual GPU"),
        vk::PhysicalDeviceType::CPU => (4, "CPU"),
        _ => (3, "other"),
    }
}

impl Gpu {
    pub fn new(opts: &GpuOptions) -> Result<Arc<Gpu>> {
        let entry = unsafe { ash::Entry::load() }.context(
            "cannot load the Vulkan loader (libvulkan.so.1); install libvulkan1 and a driver, e.g. mesa-vulkan-drivers",
        )?;
        let app = vk::ApplicationInfo::default().application_name(c"instgs-vk").api_version(vk::API_VERSION_1_1);
        let validation_layer = c"VK_LAYER_KHRONOS_validation";
        let mut layers = Vec::new();
        let mut extensions = Vec::new();
        if opts.validation {
            let available = unsafe { entry.enumerate_instance_layer_properties()? };
            if !available.iter().any(|l| l.layer_name_as_c_str() == Ok(validation_layer)) {
                bail!("validation was requested but VK_LAYER_KHRONOS_validation is not installed (Debian: apt-get install vulkan-validationlayers)");
            }
            layers.push(validation_layer.as_ptr());
            extensions.push(ash::ext::debug_utils::NAME.as_ptr());
        }
        if let Some((display, _)) = opts.window {
            extensions.extend_from_slice(
                ash_window::enumerate_required_extensions(display)
                    .context("this display has no Vulkan surface support")?,
            );
        }
        let enables = [vk::ValidationFeatureEnableEXT::SYNCHRONIZATION_VALIDATION];
        let mut features = vk::ValidationFeaturesEXT::default().enabled_validation_features(&enables);
        let mut ci = vk::InstanceCreateInfo::default()
            .application_info(&app)
            .enabled_layer_names(&layers)
            .enabled_extension_names(&extensions);
        if opts.validation {
            ci = ci.push_next(&mut features);
        }
        let instance = unsafe { entry.create_instance(&ci, None) }.context("vkCreateInstance failed")?;
        let messages = Box::new(Messages(Mutex::new(Vec::new()), opts.echo_messages));
        let debug = if opts.validation {
            let du = ash::ext::debug_utils::Instance::new(&entry, &instance);
            let ci = vk::DebugUtilsMessengerCreateInfoEXT::default()
                .message_severity(
                    vk::DebugUtilsMessageSeverityFlagsEXT::WARNING | vk::DebugUtilsMessageSeverityFlagsEXT::ERROR,
                )
                .message_type(
                    vk::DebugUtilsMessageTypeFlagsEXT::GENERAL
                        | vk::DebugUtilsMessageTypeFlagsEXT::VALIDATION
                        | vk::DebugUtilsMessageTypeFlagsEXT::PERFORMANCE,
                )
                .pfn_user_callback(Some(debug_callback))
                .user_data(&*messages as *const Messages as *mut c_void);
            let m = unsafe { du.create_debug_utils_messenger(&ci, None)? };
            Some((du, m))
        } else {
            None
        };

        let surface = match opts.window {
            Some((display, window)) => {
                let raw = unsafe { ash_window::create_surface(&entry, &instance, display, window, None) }
                    .context("cannot create a Vulkan surface for the window")?;
                Some((ash::khr::surface::Instance::new(&entry, &instance), raw))
            }
            None => None,
        };
        let physicals = unsafe { instance.enumerate_physical_devices()? };
        if physicals.is_empty() {
            bail!("no Vulkan device found; install a driver (lavapipe: apt-get install mesa-vulkan-drivers)");
        }
        let described: Vec<(vk::PhysicalDevice, String, vk::PhysicalDeviceType)> = physicals
            .iter()
            .map(|&p| {
                let props = unsafe { instance.get_physical_device_properties(p) };
                let name = props.device_name_as_c_str().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
                (p, name, props.device_type)
            })
            .collect();
        let list = || described.iter().enumerate().map(|(i, d)| format!("{i}: {}", d.1)).collect::<Vec<_>>().join(", ");
        let chosen = match &opts.device {
            Some(sel) => {
                if let Ok(i) = sel.parse::<usize>() {
                    described.get(i).ok_or_else(|| anyhow!("device index {i} out of range; devices: {}", list()))?
                } else {
                    let low = sel.to_lowercase();
                    described
                        .iter()
                        .find(|d| d.1.to_lowercase().contains(&low))
                        .ok_or_else(|| anyhow!("no Vulkan device matches '{sel}'; devices: {}", list()))?
                }
            }
            None => described.iter().min_by_key(|d| kind_rank(d.2).0).unwrap(),
        };
        let physical = chosen.0;

        let props = unsafe { instance.get_physical_device_properties(physical) };
        if vk::api_version_major(props.api_version) == 1 && vk::api_version_minor(props.api_version) < 1 {
            bail!("device '{}' supports only Vulkan 1.0; Vulkan 1.1 is needed", chosen.1);
        }
        let mut subgroup = vk::PhysicalDeviceSubgroupProperties::default();
        let mut size_control = vk::PhysicalDeviceSubgroupSizeControlProperties::default();
        let dev_exts = unsafe { instance.enumerate_device_extension_properties(physical)? };
        let has_ext = |n: &CStr| dev_exts.iter().any(|e| e.extension_name_as_c_str() == Ok(n));
        let has_size_control =
            has_ext(ash::ext::subgroup_size_control::NAME) || vk::api_version_minor(props.api_version) >= 3;
        let mut props2 = vk::PhysicalDeviceProperties2::default().push_next(&mut subgroup);
        if has_size_control {
            props2 = props2.push_next(&mut size_control);
        }
        unsafe { instance.get_physical_device_properties2(physical, &mut props2) };
        let need = vk::SubgroupFeatureFlags::BASIC | vk::SubgroupFeatureFlags::ARITHMETIC;
        if !subgroup.supported_operations.contains(need)
            || !subgroup.supported_stages.contains(vk::ShaderStageFlags::COMPUTE)
        {
            bail!("device '{}' lacks subgroup basic/arithmetic operations in compute shaders", chosen.1);
        }
        if !has_ext(ash::khr::push_descriptor::NAME) {
            bail!("device '{}' lacks VK_KHR_push_descriptor", chosen.1);
        }
        let min_subgroup_size = if has_size_control && size_control.min_subgroup_size > 0 {
            size_control.min_subgroup_size
        } else {
            subgroup.subgroup_size
        };

        let families = unsafe { instance.get_physical_device_queue_family_properties(physical) };
        let presents = |qf: usize| match &surface {
            Some((loader, raw)) => unsafe {
                loader.get_physical_device_surface_support(physical, qf as u32, *raw).unwrap_or(false)
            },
            None => true,
        };
        let (qf, qprops) = families
            .iter()
            .enumerate()
            .find(|&(i, f)| f.queue_flags.contains(vk::QueueFlags::COMPUTE) && presents(i))
            .ok_or_else(|| match surface {
                Some(_) => anyhow!("device '{}' has no compute queue that can present to the window", chosen.1),
                None => anyhow!("device '{}' has no compute queue", chosen.1),
            })?;
        let qf = qf as u32;
        let timestamp_period_ns = (qprops.timestamp_valid_bits > 0 && props.limits.timestamp_period > 0.0)
            .then_some(props.limits.timestamp_period as f64);

        let mut atomic_float = vk::PhysicalDeviceShaderAtomicFloatFeaturesEXT::default();
        let has_atomic_float = has_ext(ash::ext::shader_atomic_float::NAME);
        if has_atomic_float {
            let mut f2 = vk::PhysicalDeviceFeatures2::default().push_next(&mut atomic_float);
            unsafe { instance.get_physical_device_features2(physical, &mut f2) };
        }
        let float_atomics = has_atomic_float && atomic_float.shader_buffer_float32_atomic_add == vk::TRUE;
        let mut enable_atomic_float = vk::PhysicalDeviceShaderAtomicFloatFeaturesEXT::default()
            .shader_buffer_float32_atomics(true)
            .shader_buffer_float32_atomic_add(true);

        let prio = [1.0f32];
        let qci = [vk::DeviceQueueCreateInfo::default().queue_family_index(qf).queue_priorities(&prio)];
        let mut dexts = vec![ash::khr::push_descriptor::NAME.as_ptr()];
        if float_atomics {
            dexts.push(ash::ext::shader_atomic_float::NAME.as_ptr());
        }
        if surface.is_some() {
            if !has_ext(ash::khr::swapchain::NAME) {
                bail!("device '{}' lacks VK_KHR_swapchain", chosen.1);
            }
            dexts.push(ash::khr::swapchain::NAME.as_ptr());
        }
        let mut dci = vk::DeviceCreateInfo::default().queue_create_infos(&qci).enabled_extension_names(&dexts);
        if float_atomics {
            dci = dci.push_next(&mut enable_atomic_float);
        }
        let device = unsafe { instance.create_device(physical, &dci, None) }.context("vkCreateDevice failed")?;
        let queue = unsafe { device.get_device_queue(qf, 0) };
        let push_descriptor = ash::khr::push_descriptor::Device::new(&instance, &device);
        let surface = surface.map(|(loader, raw)| Surface {
            loader,
            raw,
            swapchain: ash::khr::swapchain::Device::new(&instance, &device),
        });
        let allocator = Allocator::new(&AllocatorCreateDesc {
            instance: instance.clone(),
            device: device.clone(),
            physical_device: physical,
            debug_settings: Default::default(),
            buffer_device_address: false,
            allocation_sizes: Default::default(),
        })?;
        let info = DeviceInfo {
            name: chosen.1.clone(),
            kind: kind_rank(chosen.2).1,
            subgroup_size: subgroup.subgroup_size,
            min_subgroup_size,
            max_storage_buffer_range: props.limits.max_storage_buffer_range as u64,
            timestamp_period_ns,
            float_atomics,
        };
        Ok(Arc::new(Gpu {
            _entry: entry,
            instance,
            debug,
            messages,
            device,
            queue,
            push_descriptor,
            allocator: ManuallyDrop::new(Mutex::new(allocator)),
            queue_lock: Mutex::new(()),
            queue_family: qf,
            physical,
            surface,
            info,
            poison: opts.poison,
        }))
    }

    /// One line describing the device, for the CLI.
    pub fn describe(&self) -> String {
        let i = &self.info;
        let atomics = if i.float_atomics { "float atomics" } else { "no float atomics (CAS fallback)" };
        format!("{} [{}], subgroup size {}, {atomics}", i.name, i.kind, i.subgroup_size)
    }

    /// Validation messages collected since the last call.
    pub fn take_validation_messages(&self) -> Vec<String> {
        std::mem::take(&mut *self.messages.0.lock().unwrap())
    }

    /// Bytes currently allocated through the allocator.
    pub fn allocated_bytes(&self) -> u64 {
        self.allocator.lock().unwrap().generate_report().total_allocated_bytes
    }

    /// Creates a buffer. Zero-size requests get a 16-byte buffer (Vulkan forbids size 0).
    pub fn buffer(
        self: &Arc<Self>,
        name: &str,
        size: u64,
        usage: vk::BufferUsageFlags,
        location: MemoryLocation,
    ) -> Result<Buffer> {
        let size = size.max(16);
        let usage = usage | vk::BufferUsageFlags::TRANSFER_SRC | vk::BufferUsageFlags::TRANSFER_DST;
        let raw = unsafe { self.device.create_buffer(&vk::BufferCreateInfo::default().size(size).usage(usage), None)? };
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
        Ok(Buffer { gpu: self.clone(), raw, alloc: Some(alloc), size, name: name.to_string() })
    }

    /// A device-local storage buffer (filled with 0xffffffff with [`GpuOptions::poison`]).
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
        let bytes: &[u8] = bytemuck::cast_slice(data);
        if bytes.is_empty() {
            return Ok(());
        }
        let mut staging =
            self.buffer("staging-up", bytes.len() as u64, vk::BufferUsageFlags::empty(), MemoryLocation::CpuToGpu)?;
        staging.mapped_mut()?[..bytes.len()].copy_from_slice(bytes);
        self.submit_and_wait(|rec| {
            rec.copy(&staging, dst, bytes.len() as u64);
            Ok(())
        })
    }

    /// Reads the first `count` elements of `src` back to the host (waits for the GPU).
    pub fn read<T: bytemuck::Pod>(self: &Arc<Self>, src: &Buffer, count: usize) -> Result<Vec<T>> {
        let bytes = (count * std::mem::size_of::<T>()) as u64;
        if bytes > src.size {
            bail!("reading {bytes} bytes from buffer '{}' of {} bytes", src.name, src.size);
        }
        if count == 0 {
            return Ok(Vec::new());
        }
        let staging = self.buffer("staging-down", bytes, vk::BufferUsageFlags::empty(), MemoryLocation::GpuToCpu)?;
        self.submit_and_wait(|rec| {
            rec.copy(src, &staging, bytes);
            Ok(())
        })?;
        let mapped = staging.mapped()?;
        Ok(bytemuck::pod_collect_to_vec(&mapped[..bytes as usize]))
    }

    /// Runs `f` with the queue, holding the lock that serialises submissions.
    pub fn with_queue<R>(&self, f: impl FnOnce(vk::Queue) -> R) -> R {
        let _q = self.queue_lock.lock().unwrap();
        f(self.queue)
    }

    pub fn queue_family(&self) -> u32 {
        self.queue_family
    }

    /// Records commands with `f`, submits them and waits for completion.
    pub fn submit_and_wait(self: &Arc<Self>, f: impl FnOnce(&mut Recorder) -> Result<()>) -> Result<()> {
        let cmd = CommandBuffer::new(self)?;
        cmd.record(|rec| f(rec))?;
        cmd.submit_and_wait()
    }
}

impl Drop for Gpu {
    fn drop(&mut self) {
        unsafe {
            let _ = self.device.device_wait_idle();
            ManuallyDrop::drop(&mut self.allocator);
            self.device.destroy_device(None);
            if let Some(s) = self.surface.take() {
                s.loader.destroy_surface(s.raw, None);
            }
            if let Some((du, m)) = self.debug.take() {
                du.destroy_debug_utils_messenger(m, None);
            }
            self.instance.destroy_instance(None);
        }
    }
}

/// A Vulkan buffer with its memory. Freed on drop.
pub struct Buffer {
    gpu: Arc<Gpu>,
    pub raw: vk::Buffer,
    alloc: Option<Allocation>,
    pub size: u64,
    pub name: String,
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

    fn mapped(&self) -> Result<&[u8]> {
        self.alloc
            .as_ref()
            .and_then(|a| a.mapped_slice())
            .ok_or_else(|| anyhow!("buffer '{}' is not host-visible", self.name))
    }

    fn mapped_mut(&mut self) -> Result<&mut [u8]> {
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
        unsafe { self.gpu.device.destroy_buffer(self.raw, None) };
    }
}

/// A compute pipeline whose descriptor layout comes from SPIR-V reflection. Buffers are bound by
/// the GLSL variable name of their block (`buffer XBuf { ... } name;`), so binding numbers exist
/// only in the kernel source.
pub struct Kernel {
    gpu: Arc<Gpu>,
    pub name: String,
    pipeline: vk::Pipeline,
    layout: vk::PipelineLayout,
    set_layout: vk::DescriptorSetLayout,
    bindings: BTreeMap<String, (u32, vk::DescriptorType)>,
    push_size: u32,
}

impl Kernel {
    /// Builds the pipeline; specialization constant 0 is the device's minimum subgroup size.
    pub fn new(gpu: &Arc<Gpu>, name: &str, spirv: &[u8]) -> Result<Kernel> {
        Kernel::with_spec(gpu, name, spirv, &[])
    }

    /// As [`Kernel::new`], with `extra[i]` as the u32 specialization constant `i + 1`.
    pub fn with_spec(gpu: &Arc<Gpu>, name: &str, spirv: &[u8], extra: &[u32]) -> Result<Kernel> {
        let refl = rspirv_reflect::Reflection::new_from_spirv(spirv)
            .map_err(|e| anyhow!("kernel {name}: SPIR-V reflection failed: {e:?}"))?;
        let sets = refl.get_descriptor_sets().map_err(|e| anyhow!("kernel {name}: reflection: {e:?}"))?;
        if sets.keys().any(|&s| s != 0) {
            bail!("kernel {name}: only descriptor set 0 is supported");
        }
        let mut bindings = BTreeMap::new();
        let mut layout_bindings = Vec::new();
        for (&binding, info) in sets.get(&0).into_iter().flatten() {
            let ty = match info.ty {
                rspirv_reflect::DescriptorType::STORAGE_BUFFER => vk::DescriptorType::STORAGE_BUFFER,
                rspirv_reflect::DescriptorType::UNIFORM_BUFFER => vk::DescriptorType::UNIFORM_BUFFER,
                other => bail!("kernel {name}: binding {binding} has unsupported descriptor type {other:?}"),
            };
            if info.name.is_empty() {
                bail!("kernel {name}: binding {binding} has no instance name; declare `buffer XBuf {{ ... }} name;`");
            }
            bindings.insert(info.name.clone(), (binding, ty));
            layout_bindings.push(
                vk::DescriptorSetLayoutBinding::default()
                    .binding(binding)
                    .descriptor_type(ty)
                    .descriptor_count(1)
                    .stage_flags(vk::ShaderStageFlags::COMPUTE),
            );
        }
        let push_size = refl
            .get_push_constant_range()
            .map_err(|e| anyhow!("kernel {name}: reflection: {e:?}"))?
            .map(|p| p.offset + p.size)
            .unwrap_or(0);
        let d = &gpu.device;
        let words = ash::util::read_spv(&mut std::io::Cursor::new(spirv))?;
        unsafe {
            let module = d.create_shader_module(&vk::ShaderModuleCreateInfo::default().code(&words), None)?;
            let set_layout = d.create_descriptor_set_layout(
                &vk::DescriptorSetLayoutCreateInfo::default()
                    .flags(vk::DescriptorSetLayoutCreateFlags::PUSH_DESCRIPTOR_KHR)
                    .bindings(&layout_bindings),
                None,
            )?;
            let ranges =
                [vk::PushConstantRange::default().stage_flags(vk::ShaderStageFlags::COMPUTE).offset(0).size(push_size)];
            let set_layouts = [set_layout];
            let mut lci = vk::PipelineLayoutCreateInfo::default().set_layouts(&set_layouts);
            if push_size > 0 {
                lci = lci.push_constant_ranges(&ranges);
            }
            let layout = d.create_pipeline_layout(&lci, None)?;
            let spec_values: Vec<u32> =
                std::iter::once(gpu.info.min_subgroup_size).chain(extra.iter().copied()).collect();
            let spec_data: &[u8] = bytemuck::cast_slice(&spec_values);
            let spec_entries: Vec<vk::SpecializationMapEntry> = (0..spec_values.len() as u32)
                .map(|i| vk::SpecializationMapEntry::default().constant_id(i).offset(4 * i).size(4))
                .collect();
            let spec = vk::SpecializationInfo::default().map_entries(&spec_entries).data(spec_data);
            let entry = CString::new("main").unwrap();
            let stage = vk::PipelineShaderStageCreateInfo::default()
                .stage(vk::ShaderStageFlags::COMPUTE)
                .module(module)
                .name(&entry)
                .specialization_info(&spec);
            let pci = [vk::ComputePipelineCreateInfo::default().stage(stage).layout(layout)];
            let pipeline = d.create_compute_pipelines(vk::PipelineCache::null(), &pci, None);
            d.destroy_shader_module(module, None);
            let pipeline = pipeline.map_err(|(_, e)| anyhow!("kernel {name}: pipeline creation failed: {e}"))?[0];
            Ok(Kernel { gpu: gpu.clone(), name: name.to_string(), pipeline, layout, set_layout, bindings, push_size })
        }
    }
}

impl Drop for Kernel {
    fn drop(&mut self) {
        unsafe {
            let d = &self.gpu.device;
            d.destroy_pipeline(self.pipeline, None);
            d.destroy_pipeline_layout(self.layout, None);
            d.destroy_descriptor_set_layout(self.set_layout, None);
        }
    }
}

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
    gpu: &'a Arc<Gpu>,
    cmd: vk::CommandBuffer,
    timer: Option<&'a mut Timer>,
}

impl Recorder<'_> {
    fn barrier(&mut self) {
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
        if binds.len() != k.bindings.len() {
            let want: Vec<&String> = k.bindings.keys().collect();
            let got: Vec<&str> = binds.iter().map(|b| b.0).collect();
            bail!("kernel {}: expects buffers {want:?}, got {got:?}", k.name);
        }
        let mut infos = Vec::with_capacity(binds.len());
        let mut meta = Vec::with_capacity(binds.len());
        for (name, buf) in binds {
            let &(binding, ty) =
                k.bindings.get(*name).ok_or_else(|| anyhow!("kernel {}: no buffer named '{name}'", k.name))?;
            if ty == vk::DescriptorType::STORAGE_BUFFER && buf.size > self.gpu.info.max_storage_buffer_range {
                bail!(
                    "buffer '{}' ({} bytes) exceeds the device's maxStorageBufferRange ({} bytes)",
                    buf.name,
                    buf.size,
                    self.gpu.info.max_storage_buffer_range
                );
            }
            infos.push([vk::DescriptorBufferInfo::default().buffer(buf.raw).offset(0).range(vk::WHOLE_SIZE)]);
            meta.push((binding, ty));
        }
        let writes: Vec<vk::WriteDescriptorSet> = infos
            .iter()
            .zip(&meta)
            .map(|(info, &(binding, ty))| {
                vk::WriteDescriptorSet::default().dst_binding(binding).descriptor_type(ty).buffer_info(info)
            })
            .collect();
        let bytes: &[u8] = bytemuck::bytes_of(push);
        if bytes.len() as u32 != k.push_size && !(k.push_size == 0 && bytes.is_empty()) {
            bail!("kernel {}: push constants are {} bytes, given {}", k.name, k.push_size, bytes.len());
        }
        unsafe {
            let d = &self.gpu.device;
            d.cmd_bind_pipeline(self.cmd, vk::PipelineBindPoint::COMPUTE, k.pipeline);
            self.gpu.push_descriptor.cmd_push_descriptor_set(
                self.cmd,
                vk::PipelineBindPoint::COMPUTE,
                k.layout,
                0,
                &writes,
            );
            if k.push_size > 0 {
                d.cmd_push_constants(self.cmd, k.layout, vk::ShaderStageFlags::COMPUTE, 0, bytes);
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
