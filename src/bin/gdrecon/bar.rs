//! A progress bar that appears only once a task has run for a second.

use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};

/// Hidden at first; shown on stderr after [`DELAY`] unless quiet.
pub struct DelayedBar {
    bar: ProgressBar,
    start: Instant,
    shown: AtomicBool,
    quiet: bool,
}

const DELAY: Duration = Duration::from_secs(1);
const STEPS: u64 = 1000;

impl DelayedBar {
    pub fn new(quiet: bool) -> Self {
        let bar = ProgressBar::with_draw_target(Some(STEPS), ProgressDrawTarget::hidden());
        bar.set_style(
            ProgressStyle::with_template("{spinner} [{elapsed_precise}] {wide_bar} {percent:>3}%")
                .expect("static template is valid"),
        );
        DelayedBar {
            bar,
            start: Instant::now(),
            shown: AtomicBool::new(false),
            quiet,
        }
    }

    /// Progress callback body: never cancels.
    pub fn update(&self, fraction: f64) -> bool {
        if !self.quiet && self.start.elapsed() > DELAY && !self.shown.swap(true, Ordering::Relaxed)
        {
            self.bar.set_draw_target(ProgressDrawTarget::stderr());
        }
        self.bar.set_position((fraction * STEPS as f64) as u64);
        true
    }

    pub fn finish(&self) {
        self.bar.finish_and_clear();
    }
}
