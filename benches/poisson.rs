//! Screened Poisson at 1280 x 720 RGB: execution time of a committed plan (planning, i.e. the
//! DCT plans and buffers, is done once outside the timed loop, as a renderer would).
//! Targets on the project's 2-core machine: L2 under 0.15 s, L1 under 1.5 s (medians).
//!
//! `cargo bench --bench poisson`

use criterion::{criterion_group, criterion_main, Criterion};
use gdrecon::recon::{PoissonL1Config, PoissonL2Config};
use gdrecon::{synth, Context, ContextOptions, Image, MethodConfig, Plan, Progress};

fn poisson(c: &mut Criterion) {
    let (w, h) = (1280, 720);
    let frame = synth::synthetic_frame(w, h, 16.0, 1);
    let ctx = Context::new(ContextOptions::default()).unwrap();
    let mut group = c.benchmark_group("poisson_1280x720");
    group.sample_size(10);
    for (name, config) in [
        ("l2", MethodConfig::PoissonL2(PoissonL2Config::default())),
        ("l1", MethodConfig::PoissonL1(PoissonL1Config::default())),
    ] {
        let mut plan = Plan::new(&ctx, &config, w, h).unwrap();
        let mut out = Image::zeros(3, w, h);
        group.bench_function(name, |b| {
            b.iter(|| {
                plan.execute_into(&frame, &mut out, &Progress::none())
                    .unwrap()
            })
        });
    }
    group.finish();
}

criterion_group!(benches, poisson);
criterion_main!(benches);
