//! What a reconstruction tells its caller besides the image: time per stage, what it skipped,
//! what it replaced.

use std::fmt;
use std::time::{Duration, Instant};

use crate::validate::SanitizeReport;

/// One timed stage of a method.
#[derive(Clone, Debug, PartialEq)]
#[non_exhaustive]
pub struct Stage {
    /// Short stage name (`"rhs"`, `"dct solve"`, `"irls"`...).
    pub name: String,
    /// Wall time spent in it.
    pub time: Duration,
}

/// The account of one reconstruction.
#[derive(Clone, Debug, Default, PartialEq)]
#[non_exhaustive]
pub struct Report {
    /// Method name as the CLI spells it.
    pub method: String,
    /// Stages in execution order.
    pub stages: Vec<Stage>,
    /// Work the method skipped because the frame did not need it (missing features, ...).
    pub skipped: Vec<String>,
    /// Other facts worth showing (iteration counts, residuals, estimated inputs).
    pub notes: Vec<String>,
    /// Values replaced while validating the input frame.
    pub sanitized: SanitizeReport,
    /// Output values that came out non-finite and were replaced by the base colour. Always 0
    /// unless a method has a bug; kept so that the guarantee "no NaN or Inf out" is checkable.
    pub output_repaired: u64,
    /// Output values that came out negative and were set to 0 (radiance is never negative, so
    /// this moves each of them closer to any reference). Screened Poisson solves produce a
    /// few where the gradients disagree with the base image, e.g. beside emitters in view.
    pub output_clamped: u64,
}

impl Report {
    /// Total time over all stages.
    pub fn total_time(&self) -> Duration {
        self.stages.iter().map(|s| s.time).sum()
    }

    /// Runs `f`, recording its wall time as stage `name`.
    pub fn time<T>(&mut self, name: &str, f: impl FnOnce() -> T) -> T {
        let start = Instant::now();
        let out = f();
        self.stages.push(Stage {
            name: name.to_owned(),
            time: start.elapsed(),
        });
        out
    }

    /// Adds a note.
    pub fn note(&mut self, note: impl Into<String>) {
        self.notes.push(note.into());
    }

    /// Records skipped work.
    pub fn skip(&mut self, what: impl Into<String>) {
        self.skipped.push(what.into());
    }
}

impl fmt::Display for Report {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(
            f,
            "method {}: {:.3} s",
            self.method,
            self.total_time().as_secs_f64()
        )?;
        for s in &self.stages {
            writeln!(f, "  {:<14} {:>9.3} s", s.name, s.time.as_secs_f64())?;
        }
        for s in &self.skipped {
            writeln!(f, "  skipped: {s}")?;
        }
        for n in &self.notes {
            writeln!(f, "  {n}")?;
        }
        writeln!(f, "  input: {}", self.sanitized)?;
        if self.output_repaired > 0 {
            writeln!(
                f,
                "  output: {} non-finite values replaced by the base colour",
                self.output_repaired
            )?;
        }
        if self.output_clamped > 0 {
            writeln!(
                f,
                "  output: {} negative values set to 0",
                self.output_clamped
            )?;
        }
        Ok(())
    }
}
