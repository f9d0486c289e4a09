//! The GPU radix sort equals a CPU stable sort, under validation layers.
mod common;
use common::*;
use instgs_vk::gpu::kernels::{KernelPolicy, Kernels};
use instgs_vk::render::reference::{self, forward::stable_sort};
use instgs_vk::render::sort::GpuSort;

#[test]
fn gpu_sort_equals_cpu_stable_sort() {
    let (gpu, _) = gpu();
    // Both policies, whatever the device: GPU-sized and CPU-sized runs per thread, 6- and 8-bit
    // digits; and the one-dispatch small-input sort with both digit widths.
    let gpu_small = KernelPolicy { sort_small_max: KernelPolicy::CPU.sort_small_max, ..KernelPolicy::GPU };
    for policy in [KernelPolicy::GPU, KernelPolicy::CPU, gpu_small] {
        let k = Kernels::with_policy(&gpu, policy).unwrap();
        check_sort(GpuSort::new(&gpu, &k, 1_000_003).unwrap());
    }
    assert_clean(&gpu);
}

fn check_sort(mut sorter: GpuSort) {
    let mut rng = Rng::new(7);
    // (count, key bits, distinct keys): few distinct keys force long runs of duplicates, so a
    // stable sort must keep the value (input index) order inside each run.
    let cases = [
        (1, 32, u32::MAX),
        (7, 32, 3),
        (4095, 8, 256),
        (4095, 32, u32::MAX),
        (4096, 12, 1000),
        (4096, 32, 17),
        (4097, 31, u32::MAX),
        // Around the CPU policy's one-dispatch limit (SORT_SMALL_MAX_CPU), odd and even passes.
        (12_288, 17, u32::MAX),
        (12_289, 17, u32::MAX),
        (12_288, 32, 40),
        (12_289, 32, 40),
        (100_000, 11, 1200),
        (1_000_003, 32, u32::MAX),
        (1_000_003, 11, 1200),
    ];
    for (n, bits, distinct) in cases {
        let mask = if bits == 32 { u32::MAX } else { (1u32 << bits) - 1 };
        let keys: Vec<u32> = (0..n)
            .map(|_| {
                let v = rng.u32();
                (if distinct == u32::MAX { v } else { v % distinct }) & mask
            })
            .collect();
        let vals: Vec<u32> = (0..n as u32).collect();
        let got = sorter.sort(&keys, &vals, bits, 1).unwrap();
        let (want_k, want_v) = stable_sort(&keys, &vals);
        assert!(got.keys == want_k, "keys differ: n={n} bits={bits}");
        assert!(got.vals == want_v, "values differ (not stable?): n={n} bits={bits}");
    }
}

#[test]
fn dispatch_args_match_cpu_twin() {
    use instgs_vk::gpu::kernels::Counts;
    use instgs_vk::shared::{ARGS_PER_SLOT, COUNT_SLOTS};
    let (gpu, _) = gpu();
    for k in both_policies() {
        let counts = Counts::new(&gpu).unwrap();
        let ns: Vec<u32> = vec![0, 1, 257, 12_288, 12_289, 4_000_000, 50_000_000, u32::MAX / 2];
        gpu.submit_and_wait(|rec| {
            rec.fill(&counts.indirect, 0xdead_beef);
            rec.update(&counts.counts, &ns);
            for slot in 0..COUNT_SLOTS {
                counts.record_args(rec, &k, slot)?;
            }
            Ok(())
        })
        .unwrap();
        let got: Vec<u32> = gpu.read(&counts.indirect, (COUNT_SLOTS * ARGS_PER_SLOT * 3) as usize).unwrap();
        for (slot, &n) in ns.iter().enumerate() {
            let want = reference::forward::dispatch_groups(n, k.sort_block(), k.policy.sort_small_max);
            for (kind, &groups) in want.iter().enumerate() {
                let at = (slot * ARGS_PER_SLOT as usize + kind) * 3;
                assert_eq!(got[at..at + 3], [groups, 1, 1], "n={n} kind={kind}");
            }
        }
    }
    assert_clean(&gpu);
}

#[test]
fn draw_args_match_cpu_twin() {
    use instgs_vk::gpu::kernels::Counts;
    use instgs_vk::shared::COUNT_VISIBLE;
    let (gpu, k) = gpu();
    let counts = Counts::new(&gpu).unwrap();
    let args = gpu.storage("draw_args", 16).unwrap();
    for n in [0u32, 1, 90_854, u32::MAX / 2] {
        gpu.write_at(&counts.counts, COUNT_VISIBLE as u64 * 4, &[n]).unwrap();
        gpu.submit_and_wait(|rec| {
            rec.fill(&args, 0xdead_beef);
            rec.dispatch(&k.draw_args, &[("counts", &counts.counts), ("draw_args", &args)], &(), [1, 1, 1])
        })
        .unwrap();
        let got: Vec<u32> = gpu.read(&args, 4).unwrap();
        assert_eq!(got, reference::forward::draw_args(n), "visible {n}");
    }
    assert_clean(&gpu);
}
