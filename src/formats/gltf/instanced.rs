//! Reading the instanced scene our `extras.instgs` describe, checked against the node tree it
//! describes (docs/robustness.md): every splat node named once, shared accessors shared, and
//! every instance's splats placed where its node places them.
use std::collections::HashMap;

use anyhow::{anyhow, bail, Context, Result};
use glam::Vec3;
use gltf::mesh::Semantic;
use serde_json::Value;

use super::read::{append_any_degree, Ctx, SplatPrimitive};
use super::{
    half_turn_z, turn_similarity, GroupExtras, InstgsExtras, EXTRAS_VERSION, PREFIX, TEMPLATE_DC,
    TEMPLATE_OPACITY_LOGIT, TEMPLATE_POSITION,
};
use crate::model::instanced::{Group, Instance, InstancedScene, Offsets, Similarity};
use crate::model::scene::Scene;

/// The instanced scene our extras describe, or why they do not match the file.
pub(super) fn read_instanced(
    ctx: &Ctx,
    doc: &gltf::Document,
    splats: &[SplatPrimitive],
    extras: &Value,
) -> Result<InstancedScene> {
    let x: InstgsExtras = serde_json::from_value(extras.clone()).context("unreadable")?;
    if x.version != EXTRAS_VERSION {
        bail!("version {} (we read {EXTRAS_VERSION})", x.version);
    }
    let by_node: HashMap<usize, &SplatPrimitive> = splats.iter().map(|p| (p.node, p)).collect();
    let named: usize = x.background.len() + x.groups.iter().map(|g| g.instances.len()).sum::<usize>();
    if by_node.len() != splats.len() || named != splats.len() {
        bail!("{} splat primitives, {} named", splats.len(), named);
    }
    // Every splat node named once: by the background or by one instance.
    let mut seen = std::collections::HashSet::new();
    for n in x.background.iter().chain(x.groups.iter().flat_map(|g| g.instances.iter().map(|i| &i.node))) {
        if !seen.insert(*n) {
            bail!("node {n} is named twice (by the background or two instances)");
        }
    }
    let node_prim =
        |n: usize| by_node.get(&n).copied().ok_or_else(|| anyhow!("node {n} is not a splat node of the scene"));
    let mut background = Scene::default();
    for &n in &x.background {
        background = append_any_degree(background, ctx.placed(node_prim(n)?, doc)?);
    }
    half_turn_z(&mut background);
    let mut groups = Vec::new();
    for g in &x.groups {
        groups.push(read_group(ctx, doc, g, &node_prim)?);
    }
    let degree = groups.iter().map(|g: &Group| g.template.sh_degree).chain([background.sh_degree]).max().unwrap_or(0);
    if groups.iter().any(|g| g.template.sh_degree != degree)
        || (!background.is_empty() && background.sh_degree != degree)
    {
        bail!("its parts have different SH degrees");
    }
    background = background.with_sh_degree(degree);
    let scene = InstancedScene { sh_degree: degree, background, groups };
    scene.validate(ctx.what)?;
    Ok(scene)
}

/// One group: its template (shared rows + its own means, logits and DC, on its first instance's
/// primitive), transforms and offsets, in our frame.
fn read_group<'a>(
    ctx: &Ctx,
    doc: &gltf::Document,
    g: &GroupExtras,
    node_prim: &dyn Fn(usize) -> Result<&'a SplatPrimitive>,
) -> Result<Group> {
    let first = g.instances.first().ok_or_else(|| anyhow!("group {:?} has no instances", g.name))?;
    let mut t = ctx.primitive(doc, node_prim(first.node)?)?;
    let first_prim = gltf_primitive(doc, node_prim(first.node)?)?;
    let own_attribute = |name: &str, dims: usize| {
        let acc = first_prim
            .attributes()
            .find_map(|(s, a)| matches!(s, Semantic::Extras(n) if n == name[1..]).then_some(a))
            .ok_or_else(|| anyhow!("group {:?}: its first instance has no {name} attribute", g.name))?;
        ctx.values(&acc, name, dims)
    };
    let (pos, logits, dc) = (
        own_attribute(TEMPLATE_POSITION, 3)?,
        own_attribute(TEMPLATE_OPACITY_LOGIT, 1)?,
        own_attribute(TEMPLATE_DC, 3)?,
    );
    let n = t.len();
    if pos.len() != n * 3 || logits.len() != n || dc.len() != n * 3 {
        bail!("group {:?}: the template's accessors hold other counts than its instances", g.name);
    }
    // Quantised positions: the instances' rows are dequantised by `d`, which their nodes
    // apply after their transforms; the shared scales were divided by its scale.
    if let Some(d) = &g.dequantise {
        d.check().with_context(|| format!("group {:?}", g.name))?;
        let ln = d.scale.ln();
        t.scales.iter_mut().flatten().for_each(|v| *v += ln);
    }
    let dequantise = g.dequantise.map_or(glam::Mat4::IDENTITY, |d| d.mat4());
    let requantise = dequantise.inverse();
    let c = t.sh_coeffs();
    let shared = shared_of(doc, node_prim(first.node)?)?;
    for j in 0..n {
        t.means[j] = [pos[j * 3], pos[j * 3 + 1], pos[j * 3 + 2]];
        t.opacities[j] = logits[j];
        t.sh[j * c * 3..j * c * 3 + 3].copy_from_slice(&dc[j * 3..j * 3 + 3]);
    }
    half_turn_z(&mut t);
    let mut instances = Vec::new();
    let mut offsets = Offsets::zeros(n * g.instances.len());
    for (k, inst) in g.instances.iter().enumerate() {
        let p = node_prim(inst.node)?;
        if shared_of(doc, p)? != shared {
            bail!("instance {:?} does not share its group's rotation, scale and SH accessors", inst.id);
        }
        let own = ctx.primitive(doc, p)?;
        if own.len() != n {
            bail!("instance {:?} has {} splats, its template {n}", inst.id, own.len());
        }
        let x = turn_similarity(&Similarity::from_mat4(p.world * requantise, "a node's matrix")?)?;
        for j in 0..n {
            let q = k * n + j;
            // The instance's template-space mean, turned into our frame.
            let m = dequantise.transform_point3(Vec3::from(own.means[j]));
            let local = Vec3::new(-m[0], -m[1], m[2]) - Vec3::from(t.means[j]);
            offsets.d_means[q] = (x.rotation * (local * x.scale)).to_array();
            offsets.d_opacities[q] = own.opacities[j] - t.opacities[j];
            for ch in 0..3 {
                offsets.d_sh0[q][ch] = own.sh[j * c * 3 + ch] - t.sh[j * c * 3 + ch];
            }
        }
        instances.push(Instance { id: inst.id.clone(), transform: x });
    }
    let group = Group { name: g.name.clone(), template: t, instances, offsets };
    agrees_with_nodes(ctx, doc, &group, g, node_prim)?;
    Ok(group)
}

/// The group our extras describe must place its splats where its instances' nodes place them
/// (within f32 rounding of the scene's size): an edit of the nodes, the accessors or the extras
/// since we wrote the file (a template moved far off leaves its offsets to carry it back, which
/// f32 cannot do exactly) makes the node tree, read plainly, the scene.
fn agrees_with_nodes<'a>(
    ctx: &Ctx,
    doc: &gltf::Document,
    group: &Group,
    g: &GroupExtras,
    node_prim: &dyn Fn(usize) -> Result<&'a SplatPrimitive>,
) -> Result<()> {
    let one = InstancedScene {
        sh_degree: group.template.sh_degree,
        background: Scene { sh_degree: group.template.sh_degree, ..Scene::default() },
        groups: vec![group.clone()],
    };
    let ours = one.expanded_means();
    let mut theirs = Vec::with_capacity(ours.len());
    for inst in &g.instances {
        let mut s = ctx.placed(node_prim(inst.node)?, doc)?;
        half_turn_z(&mut s);
        theirs.extend(s.means);
    }
    let (lo, hi) = theirs.iter().fold(([f32::MAX; 3], [f32::MIN; 3]), |(lo, hi), p| {
        (std::array::from_fn(|a| lo[a].min(p[a])), std::array::from_fn(|a| hi[a].max(p[a])))
    });
    let size = Vec3::from(hi).distance(Vec3::from(lo)).max(1e-6);
    let far = theirs.iter().map(|p| Vec3::from(*p).abs().max_element()).fold(0.0f32, f32::max).max(size);
    let tolerance = 1e-5 * far;
    let worst = ours.iter().zip(&theirs).map(|(a, b)| Vec3::from(*a).distance(Vec3::from(*b))).fold(0.0f32, f32::max);
    if ours.len() != theirs.len() || worst.is_nan() || worst > tolerance {
        bail!(
            "group {:?}: its template, transforms and offsets place splats up to {worst:.3e} from where its nodes do (more than {tolerance:.1e})",
            g.name
        );
    }
    Ok(())
}

/// The document's primitive of `p`.
fn gltf_primitive<'a>(doc: &'a gltf::Document, p: &SplatPrimitive) -> Result<gltf::Primitive<'a>> {
    doc.nodes()
        .nth(p.node)
        .and_then(|n| n.mesh())
        .and_then(|m| m.primitives().nth(p.primitive))
        .ok_or_else(|| anyhow!("no primitive"))
}

/// The accessor indices of a primitive's ROTATION, SCALE and SH rest (what instances share).
fn shared_of(doc: &gltf::Document, p: &SplatPrimitive) -> Result<Vec<(String, usize)>> {
    let mut v: Vec<(String, usize)> = gltf_primitive(doc, p)?
        .attributes()
        .filter_map(|(s, a)| match s {
            Semantic::Extras(n)
                if n.starts_with(PREFIX)
                    && (n.ends_with("ROTATION")
                        || n.ends_with("SCALE")
                        || (n.contains("SH_DEGREE_") && !n.contains("SH_DEGREE_0_"))) =>
            {
                Some((n, a.index()))
            }
            _ => None,
        })
        .collect();
    v.sort();
    Ok(v)
}
