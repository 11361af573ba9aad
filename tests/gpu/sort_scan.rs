//! GPU prefix sum and radix sort against CPU results.

use crate::common;

use rand::{RngExt, SeedableRng};
use sylva::splat::gpu::buffers::{read_buffer, storage_from};
use sylva::splat::gpu::scan::Scanner;
use sylva::splat::gpu::sort::{RadixSorter, bits_for};

#[test]
fn prefix_sum_matches_cpu() {
    let Some(ctx) = common::context() else { return };
    let scanner = Scanner::new(&ctx);
    let mut rng = rand::rngs::ChaCha8Rng::seed_from_u64(7);
    for &n in &[1usize, 5, 1024, 1025, 3000, 70_000, 1_100_000] {
        let data: Vec<u32> = (0..n).map(|_| rng.random_range(0..20)).collect();
        let buf = storage_from(&ctx, "scan test", &data).expect("buffer");
        let mut enc = ctx.device.create_command_encoder(&Default::default());
        scanner
            .encode(&ctx, &mut enc, &buf, n as u32)
            .expect("encode");
        ctx.queue.submit([enc.finish()]);
        let got: Vec<u32> = read_buffer(&ctx, &buf, n).expect("read");
        let mut acc = 0u32;
        for (i, (&g, &d)) in got.iter().zip(&data).enumerate() {
            assert_eq!(g, acc, "n = {n}, index {i}");
            acc += d;
        }
    }
}

#[test]
fn radix_sort_is_sorted_and_stable() {
    let Some(ctx) = common::context() else { return };
    let sorter = RadixSorter::new(&ctx);
    let mut rng = rand::rngs::ChaCha8Rng::seed_from_u64(11);
    for &(n, max_hi) in &[
        (2usize, 3u32),
        (1000, 0),
        (5000, 63),
        (40_000, 1000),
        (3000, 70_000),
    ] {
        let hi: Vec<u32> = (0..n).map(|_| rng.random_range(0..=max_hi)).collect();
        // Few distinct low keys so that ties are common and stability is exercised.
        let lo: Vec<u32> = (0..n)
            .map(|_| {
                if rng.random_bool(0.5) {
                    rng.random_range(0..4)
                } else {
                    rng.random()
                }
            })
            .collect();
        let val: Vec<u32> = (0..n as u32).collect();
        let bh = storage_from(&ctx, "hi", &hi).expect("buffer");
        let bl = storage_from(&ctx, "lo", &lo).expect("buffer");
        let bv = storage_from(&ctx, "val", &val).expect("buffer");
        let mut enc = ctx.device.create_command_encoder(&Default::default());
        sorter
            .encode(&ctx, &mut enc, &bh, &bl, &bv, n as u32, bits_for(max_hi))
            .expect("encode");
        ctx.queue.submit([enc.finish()]);
        let gh: Vec<u32> = read_buffer(&ctx, &bh, n).expect("read");
        let gl: Vec<u32> = read_buffer(&ctx, &bl, n).expect("read");
        let gv: Vec<u32> = read_buffer(&ctx, &bv, n).expect("read");
        let mut want: Vec<(u32, u32, u32)> = (0..n).map(|i| (hi[i], lo[i], val[i])).collect();
        want.sort_by_key(|&(h, l, _)| (h, l)); // stable
        for i in 0..n {
            assert_eq!((gh[i], gl[i], gv[i]), want[i], "n = {n}, index {i}");
        }
    }
}
