#!/usr/bin/env bash
# Side-by-side frame times against a peer renderer, web-splat (docs/benchmarking.md): builds it
# from source in a scratch folder outside the repository (with a small timing harness of ours),
# writes the same orbit cameras for both (NeRF-synthetic transforms for us, Inria cameras.json
# for it), and runs the two interleaved, A B A B: per round our `instgs-vk bench` over every
# camera, then the harness over the same cameras; the ratio of each round's median frame times
# (ours / web-splat's), and the median of those ratios.
#
# usage: tools/bench-peers.sh [--rounds R] [--frames F] [--size WxH] [--cameras N] [--forward compute|quads|auto]
#                            [--build-only] [PLY...]
#   (default: 4 rounds, 3 frames per camera, 640x480, 8 cameras; the shared guitar, biker and
#   playbot_lod2). Results: out/bench-peers/<scene>.json and a table on stdout.
# Environment: PEERS_SCRATCH (scratch folder, default ${TMPDIR:-/tmp}/instgs-peers);
#   WEB_SPLAT_GIT, CGMATH_GIT, SPLINES_GIT: where to clone web-splat and its two git
#   dependencies from (a URL or a local git directory; default GitHub);
#   INSTGS_BIN, WEB_SPLAT_HARNESS: binaries built beforehand (tools/gpu-rows.sh --prepare):
#   nothing is cloned or built; BENCH_OUT: the results folder (default out/bench-peers).
# lavapipe: web-splat's radix sort is wrong with more than one lavapipe thread for 65,536 keys
# or more, so on a CPU device both sides run with LP_NUM_THREADS=1 (the harness saves its first
# frame, web-splat-view0.png, next to ours, ours-view0.png, to check).
set -euo pipefail
cd "$(dirname "$0")/.."
repo=$(pwd)
rounds=4 frames=3 size=640x480 ncams=8 build_only=0 forward=compute
scenes=()
while [[ $# -gt 0 ]]; do
    case $1 in
        --rounds) rounds=$2; shift 2 ;;
        --frames) frames=$2; shift 2 ;;
        --size) size=$2; shift 2 ;;
        --cameras) ncams=$2; shift 2 ;;
        --forward) forward=$2; shift 2 ;;
        --build-only) build_only=1; shift ;;
        -*) echo "bench-peers.sh: unknown option $1" >&2; exit 2 ;;
        *) scenes+=("$1"); shift ;;
    esac
done
[[ ${#scenes[@]} -gt 0 ]] || scenes=(../shared/data/splats/guitar.ply ../shared/data/splats/biker.ply ../shared/data/splats/playbot_lod2.ply)
width=${size%x*} height=${size#*x}
scratch=${PEERS_SCRATCH:-${TMPDIR:-/tmp}/instgs-peers}
out=${BENCH_OUT:-$repo/out/bench-peers}
mkdir -p "$scratch" "$out"

# Pinned commits (../shared/docs/peers.md); a prebuilt harness is of the same commit.
WEB_SPLAT_REV=959a3ecc2b649a2677fa6c56f4a1a19eb4c3fc80
CGMATH_REV=ff840cbf48d79441eaac3e78155df4723511d247
SPLINES_REV=cdb1be6c7ffbfc5eee0aca91df405c62b62b2c0a
if [[ -n ${WEB_SPLAT_HARNESS:-} ]]; then
    harness=$WEB_SPLAT_HARNESS
else

checkout() { # name source rev
    local dir=$scratch/$1
    if [[ ! -d $dir/.git ]]; then
        git clone --quiet --no-checkout "$2" "$dir"
    fi
    git -C "$dir" -c advice.detachedHead=false checkout --quiet --force "$3"
}
checkout web-splat "${WEB_SPLAT_GIT:-https://github.com/KeKsBoTer/web-splat}" $WEB_SPLAT_REV
checkout cgmath "${CGMATH_GIT:-https://github.com/rustgd/cgmath}" $CGMATH_REV
checkout splines "${SPLINES_GIT:-https://github.com/KeKsBoTer/splines}" $SPLINES_REV

# The harness: loads a PLY, renders every camera of an Inria cameras.json offscreen into an
# Rgba8Unorm target (web-splat's prepare = preprocess + sort, then its render pass), one frame
# at a time, and times each by GPU timestamps written before prepare and after the render pass
# (and by the wall clock to the end of the device wait); prints the times as JSON and saves the
# first camera's frame as a PNG.
h=$scratch/web-splat-harness
mkdir -p "$h/src"
cat > "$h/Cargo.toml" <<EOF
[package]
name = "web-splat-harness"
version = "0.1.0"
edition = "2021"

[dependencies]
web_splats = { path = "../web-splat" }
wgpu = "25.0"
cgmath = { version = "0.18.0", git = "https://github.com/rustgd/cgmath" }
pollster = { version = "0.4.0", features = ["macro"] }
image = "0.25.6"

[patch."https://github.com/rustgd/cgmath"]
cgmath = { path = "../cgmath" }
[patch."https://github.com/KeKsBoTer/splines"]
splines = { path = "../splines" }

[profile.release]
strip = true
EOF
[[ -f $h/Cargo.lock ]] || cp "$scratch/web-splat/Cargo.lock" "$h/Cargo.lock"
cat > "$h/src/main.rs" <<'EOF'
use std::{fs::File, time::{Duration, Instant}};

use cgmath::Vector2;
use web_splats::{io::GenericGaussianPointCloud, GaussianRenderer, PerspectiveCamera, PointCloud, Scene, SplattingArgs, WGPUContext};

#[pollster::main]
async fn main() {
    let a: Vec<String> = std::env::args().collect();
    if a.len() != 6 {
        eprintln!("usage: web-splat-harness SCENE.ply cameras.json FRAMES WARMUP VIEW0.png");
        std::process::exit(2);
    }
    let (frames, warmup): (usize, usize) = (a[3].parse().expect("FRAMES"), a[4].parse().expect("WARMUP"));
    let scene = Scene::from_json(File::open(&a[2]).expect("cameras.json")).expect("cameras.json");
    let ctx = WGPUContext::new_instance().await;
    let (device, queue) = (&ctx.device, &ctx.queue);
    let pc = PointCloud::new(device, GenericGaussianPointCloud::load(File::open(&a[1]).expect("PLY")).expect("PLY"))
        .expect("point cloud");
    let format = wgpu::TextureFormat::Rgba8Unorm;
    let mut renderer = GaussianRenderer::new(device, queue, format, pc.sh_deg(), pc.compressed()).await;
    // Timestamps before prepare and after the render pass, read back after each frame.
    let queries = device.create_query_set(&wgpu::QuerySetDescriptor { label: None, ty: wgpu::QueryType::Timestamp, count: 2 });
    let buffer = |usage| device.create_buffer(&wgpu::BufferDescriptor { label: None, size: 16, usage, mapped_at_creation: false });
    let resolved = buffer(wgpu::BufferUsages::QUERY_RESOLVE | wgpu::BufferUsages::COPY_SRC);
    let readback = buffer(wgpu::BufferUsages::COPY_DST | wgpu::BufferUsages::MAP_READ);
    let period = queue.get_timestamp_period() as f64;
    let (mut times, mut walls) = (Vec::new(), Vec::new());
    for (c, cam) in scene.cameras(None).into_iter().enumerate() {
        let viewport = Vector2::new(cam.width, cam.height);
        let target = device.create_texture(&wgpu::TextureDescriptor {
            label: Some("target"),
            size: wgpu::Extent3d { width: cam.width, height: cam.height, depth_or_array_layers: 1 },
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format,
            usage: wgpu::TextureUsages::COPY_SRC | wgpu::TextureUsages::RENDER_ATTACHMENT,
            view_formats: &[],
        });
        let view = target.create_view(&wgpu::TextureViewDescriptor::default());
        let mut camera: PerspectiveCamera = cam.clone().into();
        camera.fit_near_far(pc.bbox());
        for f in 0..warmup + frames {
            let t0 = Instant::now();
            let mut encoder = device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: None });
            encoder.write_timestamp(&queries, 0);
            let args = SplattingArgs {
                camera,
                viewport,
                gaussian_scaling: 1.0,
                max_sh_deg: pc.sh_deg(),
                mip_splatting: None,
                kernel_size: None,
                clipping_box: None,
                walltime: Duration::from_secs(100),
                scene_center: None,
                scene_extend: None,
                background_color: wgpu::Color::BLACK,
            };
            renderer.prepare(&mut encoder, device, queue, &pc, args, &mut None);
            {
                let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
                    label: None,
                    color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                        view: &view,
                        resolve_target: None,
                        ops: wgpu::Operations { load: wgpu::LoadOp::Clear(wgpu::Color::BLACK), store: wgpu::StoreOp::Store },
                    })],
                    depth_stencil_attachment: None,
                    timestamp_writes: None,
                    occlusion_query_set: None,
                });
                renderer.render(&mut pass, &pc);
            }
            encoder.write_timestamp(&queries, 1);
            encoder.resolve_query_set(&queries, 0..2, &resolved, 0);
            encoder.copy_buffer_to_buffer(&resolved, 0, &readback, 0, 16);
            queue.submit(Some(encoder.finish()));
            readback.slice(..).map_async(wgpu::MapMode::Read, |r| r.expect("map"));
            device.poll(wgpu::PollType::Wait).expect("poll");
            let wall = t0.elapsed().as_secs_f64() * 1e3;
            let ticks: Vec<u64> = readback.slice(..).get_mapped_range().chunks(8).map(|b| u64::from_le_bytes(b.try_into().unwrap())).collect();
            readback.unmap();
            if f >= warmup {
                times.push(ticks[1].saturating_sub(ticks[0]) as f64 * period / 1e6);
                walls.push(wall);
            }
        }
        if c == 0 {
            save(device, queue, &target, &a[5]);
        }
    }
    println!("{{\"frame_ms\": {times:?}, \"wall_ms\": {walls:?}}}");
}

fn save(device: &wgpu::Device, queue: &wgpu::Queue, target: &wgpu::Texture, path: &str) {
    let (w, h) = (target.width(), target.height());
    let row = (4 * w).div_ceil(wgpu::COPY_BYTES_PER_ROW_ALIGNMENT) * wgpu::COPY_BYTES_PER_ROW_ALIGNMENT;
    let buffer = device.create_buffer(&wgpu::BufferDescriptor {
        label: None,
        size: (row * h) as u64,
        usage: wgpu::BufferUsages::COPY_DST | wgpu::BufferUsages::MAP_READ,
        mapped_at_creation: false,
    });
    let mut encoder = device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: None });
    encoder.copy_texture_to_buffer(
        target.as_image_copy(),
        wgpu::TexelCopyBufferInfo {
            buffer: &buffer,
            layout: wgpu::TexelCopyBufferLayout { offset: 0, bytes_per_row: Some(row), rows_per_image: Some(h) },
        },
        target.size(),
    );
    queue.submit(Some(encoder.finish()));
    buffer.slice(..).map_async(wgpu::MapMode::Read, |r| r.expect("map"));
    device.poll(wgpu::PollType::Wait).expect("poll");
    let data = buffer.slice(..).get_mapped_range();
    let mut pixels = Vec::with_capacity((4 * w * h) as usize);
    for y in 0..h {
        pixels.extend_from_slice(&data[(y * row) as usize..(y * row + 4 * w) as usize]);
    }
    image::RgbaImage::from_raw(w, h, pixels).expect("image").save(path).expect("PNG");
}
EOF
echo "building web-splat $WEB_SPLAT_REV and the harness in $h (~10 min the first time on two cores)" >&2
cargo build --release --quiet --manifest-path "$h/Cargo.toml" 2> "$scratch/build.log" || { cat "$scratch/build.log" >&2; exit 1; }
harness=$h/target/release/web-splat-harness
fi
[[ $build_only == 0 ]] || exit 0

if [[ -n ${INSTGS_BIN:-} ]]; then
    ours=$INSTGS_BIN
else
    cargo build --release --quiet --bin instgs-vk
    ours=$repo/target/release/instgs-vk
fi
export XDG_RUNTIME_DIR=${XDG_RUNTIME_DIR:-/tmp}
# One lavapipe thread on both sides (see above; Mesa's variable, no effect on a GPU).
export LP_NUM_THREADS=1

echo "| scene | size | ours (ms) | web-splat (ms) | ours / web-splat: median (range over rounds) |"
echo "|---|---|---|---|---|"
for ply in "${scenes[@]}"; do
    name=$(basename "$ply" .ply)
    work=$scratch/cams-$name
    mkdir -p "$work"
    # The orbit our `--orbit` draws (robust 2–98 % bounds, 50° horizontal field of view, 25° up,
    # −Y up as the shared captures), written once for both.
    python3 - "$ply" "$work" "$ncams" "$width" "$height" <<'EOF'
import json, math, os, struct, subprocess, sys
ply, work, n, w, h = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4]), int(sys.argv[5])
with open(ply, "rb") as f:
    props, count = [], 0
    while (line := f.readline().decode().strip()) != "end_header":
        if line.startswith("element vertex"):
            count = int(line.split()[2])
        elif line.startswith("property"):
            props.append(line.split()[1:])
    if any(p[0] != "float" for p in props):
        sys.exit(f"{ply}: only float PLY properties are read here")
    names = [p[1] for p in props]
    rows = struct.iter_unpack("<" + "f" * len(names), f.read(4 * len(names) * count))
    xyz = [names.index(a) for a in "xyz"]
    pts = [[r[i] for i in xyz] for r in rows]
lo, hi = [], []
for a in range(3):
    v = sorted(p[a] for p in pts)
    lo.append(v[int(0.02 * (len(v) - 1))]); hi.append(v[int(0.98 * (len(v) - 1))])
center = [0.5 * (l + u) for l, u in zip(lo, hi)]
radius = max(0.5 * math.dist(lo, hi), 1e-3)
fov_x = math.radians(50.0)
fov_min = 2 * math.atan(math.tan(0.5 * fov_x) * h / w) if h <= w else fov_x
dist = radius / math.sin(0.5 * fov_min) * 1.05
tool = os.path.join(os.getcwd(), "tools", "orbit_transforms.py")
subprocess.run([sys.executable, tool, work, "1", str(n), *map(str, center), str(dist), "25", str(w), str(h), "50"], check=True)
t = json.load(open(os.path.join(work, "transforms_test.json")))
fx = 0.5 * w / math.tan(0.5 * t["camera_angle_x"])
cams = []
for i, fr in enumerate(t["frames"]):
    m = fr["transform_matrix"]
    # OpenGL camera-to-world (x right, y up, z back) -> Inria's rows of the OpenCV camera-to-world
    # rotation (x right, y down, z forward) and the camera position.
    rot = [[m[r][0], -m[r][1], -m[r][2]] for r in range(3)]
    cams.append({"id": i, "img_name": f"view_{i:03d}", "width": w, "height": h,
                 "position": [m[r][3] for r in range(3)], "rotation": rot, "fx": fx, "fy": fx})
json.dump(cams, open(os.path.join(work, "cameras.json"), "w"), indent=1)
EOF
    for r in $(seq 1 "$rounds"); do
        "$ours" bench --scene "$ply" --cameras "$work/transforms_test.json" --width "$width" --height "$height" \
            --frames "$frames" --warmup 1 --forward "$forward" --json "$work/ours-$r.json" > /dev/null 2>&1
        "$harness" "$ply" "$work/cameras.json" "$frames" 1 "$out/$name-web-splat-view0.png" > "$work/web-splat-$r.json"
    done
    "$ours" render --scene "$ply" --cameras "$work/transforms_test.json" --width "$width" --height "$height" \
        --forward "$forward" --out "$work/ours-render" > /dev/null 2>&1
    cp "$work/ours-render/r_000.png" "$out/$name-ours-view0.png"
    python3 - "$work" "$rounds" "$out/$name.json" "$name" "$size" "$frames" $WEB_SPLAT_REV <<'EOF'
import json, statistics, sys
work, rounds, path, name, size, frames, rev = sys.argv[1:8]
med = statistics.median
ours_runs = [json.load(open(f"{work}/ours-{r}.json")) for r in range(1, int(rounds) + 1)]
peer_runs = [json.load(open(f"{work}/web-splat-{r}.json")) for r in range(1, int(rounds) + 1)]
ours = [o["frame_ms_median"] for o in ours_runs]
theirs = [med(p["frame_ms"]) for p in peer_runs]
ratios = [a / b for a, b in zip(ours, theirs)]
res = {"scene": name, "device": ours_runs[0]["device"], "forward": ours_runs[0]["forward"], "size": size,
       "frames_per_camera": int(frames),
       "web_splat": rev, "ours_frame_ms": ours, "web_splat_frame_ms": theirs,
       "web_splat_wall_ms": [med(p["wall_ms"]) for p in peer_runs],
       "ratio_per_round": ratios, "ratio_median": med(ratios)}
json.dump(res, open(path, "w"), indent=1)
print(f"| {name} | {size} | {med(ours):.1f} | {med(theirs):.1f} | {med(ratios):.2f} ({min(ratios):.2f}–{max(ratios):.2f}) |")
EOF
done
