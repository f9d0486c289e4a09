//! The Vulkan context: instance, device choice, validation messages, queue, allocator and the
//! optional window surface.
use std::ffi::{c_void, CStr};
use std::mem::ManuallyDrop;
use std::sync::{Arc, Mutex};

use anyhow::{anyhow, bail, Context, Result};
use ash::vk;
use gpu_allocator::vulkan::{Allocator, AllocatorCreateDesc};

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
    /// The driver's name and version as it reports them (VkPhysicalDeviceDriverProperties,
    /// Vulkan 1.2), e.g. "NVIDIA 550.54.15" or "llvmpipe Mesa 22.3.6"; the API version without it.
    pub driver: String,
    /// Subgroup size the device reports (lavapipe: 8).
    pub subgroup_size: u32,
    /// Smallest subgroup size the device may use (bounds shared arrays per subgroup).
    pub min_subgroup_size: u32,
    pub max_storage_buffer_range: u64,
    /// `maxTexelBufferElements`: the most texels a kernel's `samplerBuffer` may view.
    pub max_texel_buffer_elements: u64,
    /// Nanoseconds per timestamp tick; `None` when the compute queue has no timestamps.
    pub timestamp_period_ns: Option<f64>,
    /// `shaderBufferFloat32AtomicAdd` (VK_EXT_shader_atomic_float) is available and enabled;
    /// without it the gradient kernels use their compare-and-swap variants.
    pub float_atomics: bool,
    /// The queue also draws, and [`TARGET_FORMAT`] attachments blend: the hardware-rasterized
    /// forward path (`render::raster::quads`) can run.
    pub draws: bool,
}

/// The draw path's colour attachment (crate::gpu::draw): 32-bit float RGBA, the compute path's
/// `out_image` texel.
pub const TARGET_FORMAT: vk::Format = vk::Format::R32G32B32A32_SFLOAT;

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
    debug: Option<Messenger>,
    messages: Box<Messages>,
    pub device: ash::Device,
    pub(crate) queue: vk::Queue,
    pub push_descriptor: ash::khr::push_descriptor::Device,
    pub(crate) allocator: ManuallyDrop<Mutex<Allocator>>,
    /// Submissions to `queue` must be externally synchronised.
    pub(crate) queue_lock: Mutex<()>,
    pub(crate) queue_family: u32,
    pub physical: vk::PhysicalDevice,
    pub surface: Option<Surface>,
    pub info: DeviceInfo,
    pub(crate) poison: bool,
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

type Messenger = (ash::ext::debug_utils::Instance, vk::DebugUtilsMessengerEXT);
type Described = (vk::PhysicalDevice, String, vk::PhysicalDeviceType);

/// The instance, with the validation layer (synchronization validation on) and a messenger
/// collecting its messages when `opts.validation`, and the window's surface extensions.
fn create_instance(opts: &GpuOptions) -> Result<(ash::Entry, ash::Instance, Box<Messages>, Option<Messenger>)> {
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
            ash_window::enumerate_required_extensions(display).context("this display has no Vulkan surface support")?,
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
    Ok((entry, instance, messages, debug))
}

/// The device `selector` names (an index or a case-insensitive name substring), else the best
/// kind: a discrete GPU over an integrated one over a CPU device.
fn choose_device(instance: &ash::Instance, selector: Option<&str>) -> Result<Described> {
    let physicals = unsafe { instance.enumerate_physical_devices()? };
    if physicals.is_empty() {
        bail!("no Vulkan device found; install a driver (lavapipe: apt-get install mesa-vulkan-drivers)");
    }
    let described: Vec<Described> = physicals
        .iter()
        .map(|&p| {
            let props = unsafe { instance.get_physical_device_properties(p) };
            let name = props.device_name_as_c_str().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
            (p, name, props.device_type)
        })
        .collect();
    let list = || described.iter().enumerate().map(|(i, d)| format!("{i}: {}", d.1)).collect::<Vec<_>>().join(", ");
    let chosen = match selector {
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
    Ok(chosen.clone())
}

/// What the kernels need of a device, checked: Vulkan 1.1, subgroup arithmetic in compute
/// shaders, push descriptors; with the driver's description and the subgroup sizes.
struct Capabilities {
    props: vk::PhysicalDeviceProperties,
    extensions: Vec<vk::ExtensionProperties>,
    driver: String,
    subgroup_size: u32,
    min_subgroup_size: u32,
}

impl Capabilities {
    fn query(instance: &ash::Instance, physical: vk::PhysicalDevice, name: &str) -> Result<Capabilities> {
        let props = unsafe { instance.get_physical_device_properties(physical) };
        if vk::api_version_major(props.api_version) == 1 && vk::api_version_minor(props.api_version) < 1 {
            bail!("device '{name}' supports only Vulkan 1.0; Vulkan 1.1 is needed");
        }
        let extensions = unsafe { instance.enumerate_device_extension_properties(physical)? };
        let has_ext = |n: &CStr| extensions.iter().any(|e| e.extension_name_as_c_str() == Ok(n));
        let mut subgroup = vk::PhysicalDeviceSubgroupProperties::default();
        let mut size_control = vk::PhysicalDeviceSubgroupSizeControlProperties::default();
        let has_size_control =
            has_ext(ash::ext::subgroup_size_control::NAME) || vk::api_version_minor(props.api_version) >= 3;
        let mut driver_props = vk::PhysicalDeviceDriverProperties::default();
        let has_driver_props =
            has_ext(ash::khr::driver_properties::NAME) || vk::api_version_minor(props.api_version) >= 2;
        let mut props2 = vk::PhysicalDeviceProperties2::default().push_next(&mut subgroup);
        if has_size_control {
            props2 = props2.push_next(&mut size_control);
        }
        if has_driver_props {
            props2 = props2.push_next(&mut driver_props);
        }
        unsafe { instance.get_physical_device_properties2(physical, &mut props2) };
        let api = format!(
            "Vulkan {}.{}.{}",
            vk::api_version_major(props.api_version),
            vk::api_version_minor(props.api_version),
            vk::api_version_patch(props.api_version)
        );
        let driver = if has_driver_props {
            let text = |c: Result<&CStr, _>| c.map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
            let (dname, info) = (text(driver_props.driver_name_as_c_str()), text(driver_props.driver_info_as_c_str()));
            format!("{dname} {info} ({api})").trim().to_string()
        } else {
            api
        };
        let need = vk::SubgroupFeatureFlags::BASIC | vk::SubgroupFeatureFlags::ARITHMETIC;
        if !subgroup.supported_operations.contains(need)
            || !subgroup.supported_stages.contains(vk::ShaderStageFlags::COMPUTE)
        {
            bail!("device '{name}' lacks subgroup basic/arithmetic operations in compute shaders");
        }
        if !has_ext(ash::khr::push_descriptor::NAME) {
            bail!("device '{name}' lacks VK_KHR_push_descriptor");
        }
        let min_subgroup_size = if has_size_control && size_control.min_subgroup_size > 0 {
            size_control.min_subgroup_size
        } else {
            subgroup.subgroup_size
        };
        Ok(Capabilities { props, driver, subgroup_size: subgroup.subgroup_size, min_subgroup_size, extensions })
    }

    fn has_ext(&self, n: &CStr) -> bool {
        self.extensions.iter().any(|e| e.extension_name_as_c_str() == Ok(n))
    }
}

/// The queue family to use: one that computes and draws (every desktop driver's first), else one
/// that computes; with a window, one that can also present to it.
fn queue_family(
    instance: &ash::Instance,
    physical: vk::PhysicalDevice,
    surface: Option<&(ash::khr::surface::Instance, vk::SurfaceKHR)>,
    name: &str,
) -> Result<(u32, vk::QueueFamilyProperties)> {
    let families = unsafe { instance.get_physical_device_queue_family_properties(physical) };
    let presents = |qf: usize| match surface {
        Some((loader, raw)) => unsafe {
            loader.get_physical_device_surface_support(physical, qf as u32, *raw).unwrap_or(false)
        },
        None => true,
    };
    let graphics = vk::QueueFlags::COMPUTE | vk::QueueFlags::GRAPHICS;
    let (qf, qprops) = families
        .iter()
        .enumerate()
        .find(|&(i, f)| f.queue_flags.contains(graphics) && presents(i))
        .or_else(|| {
            families.iter().enumerate().find(|&(i, f)| f.queue_flags.contains(vk::QueueFlags::COMPUTE) && presents(i))
        })
        .ok_or_else(|| match surface {
            Some(_) => anyhow!("device '{name}' has no compute queue that can present to the window"),
            None => anyhow!("device '{name}' has no compute queue"),
        })?;
    Ok((qf as u32, *qprops))
}

impl Gpu {
    pub fn new(opts: &GpuOptions) -> Result<Arc<Gpu>> {
        let (entry, instance, messages, debug) = create_instance(opts)?;
        let surface = match opts.window {
            Some((display, window)) => {
                let raw = unsafe { ash_window::create_surface(&entry, &instance, display, window, None) }
                    .context("cannot create a Vulkan surface for the window")?;
                Some((ash::khr::surface::Instance::new(&entry, &instance), raw))
            }
            None => None,
        };
        let (physical, name, device_type) = choose_device(&instance, opts.device.as_deref())?;
        let caps = Capabilities::query(&instance, physical, &name)?;
        let props = &caps.props;
        let (qf, qprops) = queue_family(&instance, physical, surface.as_ref(), &name)?;
        let timestamp_period_ns = (qprops.timestamp_valid_bits > 0 && props.limits.timestamp_period > 0.0)
            .then_some(props.limits.timestamp_period as f64);

        let mut atomic_float = vk::PhysicalDeviceShaderAtomicFloatFeaturesEXT::default();
        let has_atomic_float = caps.has_ext(ash::ext::shader_atomic_float::NAME);
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
            if !caps.has_ext(ash::khr::swapchain::NAME) {
                bail!("device '{name}' lacks VK_KHR_swapchain");
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
            kind: kind_rank(device_type).1,
            driver: caps.driver.clone(),
            subgroup_size: caps.subgroup_size,
            min_subgroup_size: caps.min_subgroup_size,
            max_storage_buffer_range: props.limits.max_storage_buffer_range as u64,
            max_texel_buffer_elements: props.limits.max_texel_buffer_elements as u64,
            timestamp_period_ns,
            float_atomics,
            draws: qprops.queue_flags.contains(vk::QueueFlags::GRAPHICS) && {
                let f = unsafe { instance.get_physical_device_format_properties(physical, TARGET_FORMAT) };
                f.optimal_tiling_features
                    .contains(vk::FormatFeatureFlags::COLOR_ATTACHMENT_BLEND | vk::FormatFeatureFlags::TRANSFER_SRC)
            },
            name,
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

    /// Runs `f` with the queue, holding the lock that serialises submissions.
    pub fn with_queue<R>(&self, f: impl FnOnce(vk::Queue) -> R) -> R {
        let _q = self.queue_lock.lock().unwrap();
        f(self.queue)
    }

    pub fn queue_family(&self) -> u32 {
        self.queue_family
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
