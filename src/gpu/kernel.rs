//! One compute kernel: its pipeline and a descriptor layout reflected from its SPIR-V; buffers
//! are bound by the GLSL name of their block, or of their `samplerBuffer` / `usamplerBuffer`
//! (bound as an RGBA32F / RGBA32UI view of the buffer); the draw path's pipelines reflect the
//! same way.
use std::collections::BTreeMap;
use std::ffi::CString;
use std::sync::Arc;

use anyhow::{anyhow, bail, Result};
use ash::vk;

use crate::gpu::context::Gpu;

/// A compute pipeline whose descriptor layout comes from SPIR-V reflection. Buffers are bound by
/// the GLSL variable name of their block (`buffer XBuf { ... } name;`), so binding numbers exist
/// only in the kernel source.
pub struct Kernel {
    pub(crate) gpu: Arc<Gpu>,
    pub name: String,
    pub(crate) pipeline: vk::Pipeline,
    pub(crate) layout: vk::PipelineLayout,
    pub(crate) set_layout: vk::DescriptorSetLayout,
    pub(crate) bindings: BTreeMap<String, Binding>,
    pub(crate) push_size: u32,
}

impl Kernel {
    /// Builds the pipeline; specialization constant 0 is the device's minimum subgroup size.
    pub fn new(gpu: &Arc<Gpu>, name: &str, spirv: &[u8]) -> Result<Kernel> {
        Kernel::with_spec(gpu, name, spirv, &[])
    }

    /// As [`Kernel::new`], with `extra[i]` as the u32 specialization constant `i + 1`.
    pub fn with_spec(gpu: &Arc<Gpu>, name: &str, spirv: &[u8], extra: &[u32]) -> Result<Kernel> {
        let Reflected { bindings, layout_bindings, push_size } =
            reflect(name, &[spirv], vk::ShaderStageFlags::COMPUTE)?;
        let d = &gpu.device;
        let words = ash::util::read_spv(&mut std::io::Cursor::new(spirv))?;
        let (set_layout, layout) = create_layouts(gpu, &layout_bindings, push_size, vk::ShaderStageFlags::COMPUTE)?;
        unsafe {
            let module = d.create_shader_module(&vk::ShaderModuleCreateInfo::default().code(&words), None)?;
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

impl Kernel {
    pub(crate) fn pipeline_ref(&self) -> PipelineRef<'_> {
        PipelineRef {
            name: &self.name,
            pipeline: self.pipeline,
            layout: self.layout,
            bindings: &self.bindings,
            push_size: self.push_size,
            point: vk::PipelineBindPoint::COMPUTE,
            stages: vk::ShaderStageFlags::COMPUTE,
        }
    }
}

/// What binding buffers to a pipeline needs: compute kernels and the draw pipelines alike.
pub(crate) struct PipelineRef<'a> {
    pub name: &'a str,
    pub pipeline: vk::Pipeline,
    pub layout: vk::PipelineLayout,
    pub bindings: &'a BTreeMap<String, Binding>,
    pub push_size: u32,
    pub point: vk::PipelineBindPoint,
    pub stages: vk::ShaderStageFlags,
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

/// One binding of a kernel's descriptor set, by reflection.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Binding {
    pub binding: u32,
    pub ty: vk::DescriptorType,
    /// The texel format of a `samplerBuffer` (RGBA32F) or `usamplerBuffer` (RGBA32UI) binding;
    /// `UNDEFINED` for buffers.
    pub format: vk::Format,
}

/// The buffers and push constants shaders declare, by reflection.
pub(crate) struct Reflected {
    /// GLSL block instance name → (binding, descriptor type).
    pub bindings: BTreeMap<String, Binding>,
    pub layout_bindings: Vec<vk::DescriptorSetLayoutBinding<'static>>,
    /// Bytes of the push-constant block (0: none).
    pub push_size: u32,
}

/// The push-descriptor set layout of `bindings` and a pipeline layout with it and `push_size`
/// bytes of push constants visible to `stages` (compute kernels and the draw pipelines alike).
pub(crate) fn create_layouts(
    gpu: &Gpu,
    bindings: &[vk::DescriptorSetLayoutBinding],
    push_size: u32,
    stages: vk::ShaderStageFlags,
) -> Result<(vk::DescriptorSetLayout, vk::PipelineLayout)> {
    let d = &gpu.device;
    unsafe {
        let set_layout = d.create_descriptor_set_layout(
            &vk::DescriptorSetLayoutCreateInfo::default()
                .flags(vk::DescriptorSetLayoutCreateFlags::PUSH_DESCRIPTOR_KHR)
                .bindings(bindings),
            None,
        )?;
        let set_layouts = [set_layout];
        let ranges = [vk::PushConstantRange::default().stage_flags(stages).offset(0).size(push_size)];
        let mut lci = vk::PipelineLayoutCreateInfo::default().set_layouts(&set_layouts);
        if push_size > 0 {
            lci = lci.push_constant_ranges(&ranges);
        }
        match d.create_pipeline_layout(&lci, None) {
            Ok(layout) => Ok((set_layout, layout)),
            Err(e) => {
                d.destroy_descriptor_set_layout(set_layout, None);
                Err(e.into())
            }
        }
    }
}

/// Reflects the descriptor set 0 and push constants of `modules` (the stages of one pipeline;
/// a binding declared by several must have one name), visible to `stages`.
pub(crate) fn reflect(name: &str, modules: &[&[u8]], stages: vk::ShaderStageFlags) -> Result<Reflected> {
    let mut bindings: BTreeMap<String, Binding> = BTreeMap::new();
    let mut push_size = 0;
    for spirv in modules {
        let refl = rspirv_reflect::Reflection::new_from_spirv(spirv)
            .map_err(|e| anyhow!("kernel {name}: SPIR-V reflection failed: {e:?}"))?;
        let sets = refl.get_descriptor_sets().map_err(|e| anyhow!("kernel {name}: reflection: {e:?}"))?;
        if sets.keys().any(|&s| s != 0) {
            bail!("kernel {name}: only descriptor set 0 is supported");
        }
        for (&binding, info) in sets.get(&0).into_iter().flatten() {
            let ty = match info.ty {
                rspirv_reflect::DescriptorType::STORAGE_BUFFER => vk::DescriptorType::STORAGE_BUFFER,
                rspirv_reflect::DescriptorType::UNIFORM_BUFFER => vk::DescriptorType::UNIFORM_BUFFER,
                rspirv_reflect::DescriptorType::UNIFORM_TEXEL_BUFFER => vk::DescriptorType::UNIFORM_TEXEL_BUFFER,
                other => bail!("kernel {name}: binding {binding} has unsupported descriptor type {other:?}"),
            };
            if info.name.is_empty() {
                bail!(
                    "kernel {name}: binding {binding} has no instance name; declare `buffer XBuf {{ ... }} name;` \\
                     (or `uniform samplerBuffer name;`)"
                );
            }
            if let Some(other) = bindings.iter().find(|(n, b)| b.binding == binding && **n != info.name) {
                bail!("kernel {name}: binding {binding} is '{}' in one stage and '{}' in another", other.0, info.name);
            }
            let format = if ty == vk::DescriptorType::UNIFORM_TEXEL_BUFFER {
                if texel_buffer_is_uint(&refl.0, binding) {
                    vk::Format::R32G32B32A32_UINT
                } else {
                    vk::Format::R32G32B32A32_SFLOAT
                }
            } else {
                vk::Format::UNDEFINED
            };
            bindings.insert(info.name.clone(), Binding { binding, ty, format });
        }
        let push = refl
            .get_push_constant_range()
            .map_err(|e| anyhow!("kernel {name}: reflection: {e:?}"))?
            .map(|p| p.offset + p.size)
            .unwrap_or(0);
        push_size = push_size.max(push);
    }
    let layout_bindings = bindings
        .values()
        .map(|b| {
            vk::DescriptorSetLayoutBinding::default()
                .binding(b.binding)
                .descriptor_type(b.ty)
                .descriptor_count(1)
                .stage_flags(stages)
        })
        .collect();
    Ok(Reflected { bindings, layout_bindings, push_size })
}

/// Whether the texel buffer at set 0 `binding` samples integers (`usamplerBuffer`): the
/// variable's type is a pointer to a sampled image whose image type has an integer sampled type.
fn texel_buffer_is_uint(module: &rspirv_reflect::rspirv::dr::Module, binding: u32) -> bool {
    use rspirv_reflect::rspirv::dr::Operand;
    use rspirv_reflect::spirv::{Decoration, Op};
    let find = |id: u32| module.types_global_values.iter().find(|i| i.result_id == Some(id));
    let var = module.annotations.iter().find_map(|a| match a.operands.as_slice() {
        [Operand::IdRef(id), Operand::Decoration(Decoration::Binding), Operand::LiteralBit32(b)] if *b == binding => {
            Some(*id)
        }
        _ => None,
    });
    let mut ty = var.and_then(find).and_then(|v| v.result_type);
    // pointer -> sampled image -> image -> sampled type
    for (op, operand) in [(Op::TypePointer, 1), (Op::TypeSampledImage, 0), (Op::TypeImage, 0)] {
        ty = ty.and_then(find).filter(|i| i.class.opcode == op).and_then(|i| i.operands.get(operand)?.id_ref_any());
    }
    ty.and_then(find).is_some_and(|i| i.class.opcode == Op::TypeInt)
}
