//! Reconstruct one frame bundle with screened Poisson L2 and L1 and compare with its reference:
//! read (validate, sanitise), plan once per size, execute, measure, write.
//!
//! `cargo run --release --example 01_reconstruct [BUNDLE.exr]` (default: the bundled sample).

use gdrecon::{io, metrics, Context, ContextOptions, Method, MethodConfig, Plan, Policy, Progress};

fn main() -> gdrecon::Result<()> {
    let path = std::env::args()
        .nth(1)
        .unwrap_or_else(|| "examples/data/sample.exr".to_owned());
    let frame = io::read_bundle(&path, Policy::Replace)?;
    let ctx = Context::new(ContextOptions::default())?;
    for method in [Method::PoissonL2, Method::PoissonL1] {
        let config = MethodConfig::default_for(method);
        let mut plan = Plan::new(&ctx, &config, frame.width(), frame.height())?;
        let (image, report) = plan.execute(&frame, &Progress::none())?;
        print!("{report}");
        if let Some(reference) = frame.reference() {
            println!("  {}", metrics::compare(&image, reference)?);
        }
        io::write_rgb(format!("{method}.exr"), &image)?;
    }
    Ok(())
}
