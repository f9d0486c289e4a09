//! `instgs-vk info`: what a scene file holds (format, counts, bounds, sizes), as text or JSON.
use std::path::Path;

use anyhow::{Context, Result};

use crate::formats::instgs;

/// Prints what `path` holds (a plain scene in any readable format, or an `.instgs`).
pub fn info(path: &Path, json: bool) -> Result<()> {
    let format = crate::formats::detect(path)?;
    if format == crate::formats::Format::Instgs {
        return info_instgs(path, json);
    }
    // An instanced glTF: its groups said, its splats described expanded.
    let (scene, instanced) = match format {
        crate::formats::Format::Gltf => match crate::formats::AnyScene::read(path)? {
            crate::formats::AnyScene::Plain(s) => (s, None),
            crate::formats::AnyScene::Instanced(s) => {
                let counts = (s.groups.len(), s.groups.iter().map(|g| g.instances.len()).sum::<usize>(), s.rows());
                (s.expand(), Some(counts))
            }
        },
        _ => (crate::formats::read_scene(path)?, None),
    };
    let file_bytes = crate::formats::file_bytes(path)?;
    let (lo, hi) = scene.bounds();
    let (rlo, rhi) = scene.robust_bounds(0.02);
    if json {
        let v = serde_json::json!({
            "file": path.display().to_string(),
            "kind": if instanced.is_some() { "instanced" } else { "plain" },
            "instanced": instanced.map(|(g, k, r)| serde_json::json!({"groups": g, "instances": k, "rows": r})),
            "format": format.name(),
            "gaussians": scene.len(),
            "sh_degree": scene.sh_degree,
            "bounds_min": lo.to_array(),
            "bounds_max": hi.to_array(),
            "bounds_min_p2": rlo.to_array(),
            "bounds_max_p98": rhi.to_array(),
            "file_bytes": file_bytes,
        });
        println!("{}", serde_json::to_string_pretty(&v)?);
    } else {
        println!("file        {}", path.display());
        println!("format      {}", format.name());
        println!("gaussians   {}", scene.len());
        if let Some((g, k, r)) = instanced {
            println!("instanced   {g} groups, {k} instances, {r} parameter rows (templates shared)");
        }
        println!("sh degree   {}", scene.sh_degree);
        println!("bounds      [{:.4}, {:.4}, {:.4}] .. [{:.4}, {:.4}, {:.4}]", lo.x, lo.y, lo.z, hi.x, hi.y, hi.z);
        println!(
            "p2..p98     [{:.4}, {:.4}, {:.4}] .. [{:.4}, {:.4}, {:.4}]",
            rlo.x, rlo.y, rlo.z, rhi.x, rhi.y, rhi.z
        );
        println!("file size   {file_bytes} bytes");
    }
    Ok(())
}

fn info_instgs(path: &Path, json: bool) -> Result<()> {
    let bytes = std::fs::read(path).with_context(|| format!("{}: cannot read", path.display()))?;
    let scene = instgs::from_bytes(&bytes, &path.display().to_string())?;
    let parts = instgs::part_bytes(&bytes)?;
    let splats = scene.splats();
    // A plain PLY of the expanded scene: 62 floats per splat at degree 3 (x y z, nx ny nz,
    // 3 f_dc, 45 f_rest, opacity, 3 scales, 4 rot), fewer at lower degrees; header excluded.
    let floats = 17 + 3 * (scene.background.sh_coeffs() - 1);
    let expanded_ply_bytes = (splats * floats * 4) as u64;
    if json {
        let groups: Vec<_> = scene
            .groups
            .iter()
            .map(|g| {
                serde_json::json!({
                    "name": g.name,
                    "template_gaussians": g.template.len(),
                    "instances": g.instances.iter().map(|i| serde_json::json!({
                        "id": i.id,
                        "transform": crate::model::instanced::mat4_to_rows(i.transform.to_mat4()),
                    })).collect::<Vec<_>>(),
                })
            })
            .collect();
        let v = serde_json::json!({
            "file": path.display().to_string(),
            "kind": "instanced",
            "sh_degree": scene.sh_degree,
            "background_gaussians": scene.background.len(),
            "parameter_rows": scene.rows(),
            "splats": splats,
            "groups": groups,
            "parts": parts,
            "file_bytes": bytes.len(),
            "expanded_ply_vertex_bytes": expanded_ply_bytes,
        });
        println!("{}", serde_json::to_string_pretty(&v)?);
    } else {
        println!("file          {}", path.display());
        println!("sh degree     {}", scene.sh_degree);
        println!("background    {} Gaussians", scene.background.len());
        for g in &scene.groups {
            println!("group {:?}: {} template Gaussians x {} instances", g.name, g.template.len(), g.instances.len());
            for i in &g.instances {
                let t = i.transform;
                println!(
                    "  instance {:?}: scale {:.4}, translation {}, rotation (w,x,y,z) {:?}",
                    i.id,
                    t.scale,
                    t.translation,
                    t.quat_wxyz()
                );
            }
        }
        println!("splats        {splats} expanded ({} parameter rows)", scene.rows());
        for p in &parts {
            println!("  {:<22} {} bytes", p.name, p.bytes);
        }
        println!("file size     {} bytes (expanded plain PLY: {expanded_ply_bytes} bytes of vertex data)", bytes.len());
    }
    Ok(())
}
