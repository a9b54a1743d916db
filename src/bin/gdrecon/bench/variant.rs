//! Named method variants: `METHOD[:OPTION[:OPTION...]]`, e.g. `l1:irls=5` or `filter:guide=l1`.
//!
//! A variant starts from the command line's method settings ([`MethodArgs`]), switches the
//! method and applies its options, so `MethodArgs::config` stays the one place that turns
//! settings into a library [`MethodConfig`].

use gdrecon::recon::FilterConfig;
use gdrecon::{Method, MethodConfig};

use crate::{GuideArg, L1Preset, MethodArgs};

/// One method at one group of settings, as timed and reported by `bench`.
#[derive(Clone, Debug)]
pub struct Variant {
    /// The method's CLI name (`l2`, `l1`, `filter`, `gradnet`).
    pub method: String,
    /// The options after the method name (`irls=5`), or `default`.
    pub setting: String,
    /// The library configuration the variant runs.
    pub config: MethodConfig,
}

impl Variant {
    /// The variant's name as given on the command line: `l1`, `l1:irls=5`.
    pub fn label(&self) -> String {
        if self.setting == DEFAULT_SETTING {
            self.method.clone()
        } else {
            format!("{}:{}", self.method, self.setting)
        }
    }
}

/// The setting name of a variant without options.
pub const DEFAULT_SETTING: &str = "default";

/// The speed/quality variants `--sweep` times for each method (a method without any: its
/// default settings alone).
pub fn sweep_names(method: Method) -> Vec<String> {
    let names: &[&str] = match method {
        Method::PoissonL1 => &["l1", "l1:irls=5", "l1:published"],
        Method::Filter => &[
            "filter",
            "filter:reference",
            "filter:levels=1",
            "filter:guide=l1",
            "filter:enhance=0",
            "filter:guide=none",
            "filter:noprefilter",
        ],
        Method::GradNet => &["gradnet", "gradnet:nofeat", "gradnet:nobias"],
        _ => return vec![method.name().to_owned()],
    };
    names.iter().map(|s| (*s).to_owned()).collect()
}

/// The variant names for `--methods` (each at its default settings, or its sweep).
pub fn names_for_methods(methods: &str, sweep: bool) -> gdrecon::Result<Vec<String>> {
    let mut names = Vec::new();
    for m in split_list(methods) {
        let method: Method = m.parse()?;
        if sweep {
            names.extend(sweep_names(method));
        } else {
            names.push(method.name().to_owned());
        }
    }
    Ok(names)
}

/// Non-empty, trimmed items of a comma-separated list.
pub fn split_list(list: &str) -> impl Iterator<Item = &str> {
    list.split(',').map(str::trim).filter(|s| !s.is_empty())
}

/// Parses a variant name on top of the command line's settings `base`.
pub fn parse(name: &str, base: &MethodArgs) -> gdrecon::Result<Variant> {
    let mut parts = name.split(':').map(str::trim);
    let method_name = parts.next().unwrap_or_default();
    let method: Method = method_name.parse().map_err(|e| bad(name, &message(e)))?;
    let mut args = base.clone();
    args.method = method.name().to_owned();
    let mut options = Vec::new();
    for option in parts {
        apply_option(method, option, &mut args).map_err(|why| bad(name, &why))?;
        options.push(option);
    }
    let config = args.config().map_err(|e| bad(name, &message(e)))?;
    let setting = if options.is_empty() {
        DEFAULT_SETTING.to_owned()
    } else {
        options.join(":")
    };
    Ok(Variant {
        method: method.name().to_owned(),
        setting,
        config,
    })
}

/// An error naming the variant.
fn bad(name: &str, why: &str) -> gdrecon::Error {
    gdrecon::Error::InvalidArgument(format!("variant '{name}': {why}"))
}

/// An error's text without its category, when that is "invalid argument" (added again by
/// [`bad`]).
fn message(e: gdrecon::Error) -> String {
    match e {
        gdrecon::Error::InvalidArgument(m) => m,
        other => other.to_string(),
    }
}

/// The options each method takes, for error messages.
fn options_help(method: Method) -> &'static str {
    match method {
        Method::PoissonL2 => "alpha=X",
        Method::PoissonL1 => "alpha=X, irls=N, cg=N, tol=X, published, fast",
        Method::Filter => {
            "levels=N, radius=N, enhance=N (0: off), guide=rdfc|l1|none, noprefilter, reference"
        }
        Method::GradNet => "nofeat, nobias, tile=N",
        _ => "none",
    }
}

/// Applies one `key=value` or flag option of `method` to `args`.
fn apply_option(method: Method, option: &str, args: &mut MethodArgs) -> Result<(), String> {
    let (key, value) = match option.split_once('=') {
        Some((k, v)) => (k.trim(), Some(v.trim())),
        None => (option, None),
    };
    let known = match (method, key, value) {
        (Method::PoissonL2 | Method::PoissonL1, "alpha", Some(v)) => {
            args.alpha = number(key, v)?;
            true
        }
        (Method::PoissonL1, "irls", Some(v)) => {
            args.irls_steps = Some(number(key, v)?);
            true
        }
        (Method::PoissonL1, "cg", Some(v)) => {
            args.cg_iterations = Some(number(key, v)?);
            true
        }
        (Method::PoissonL1, "tol", Some(v)) => {
            args.cg_tolerance = Some(number(key, v)?);
            true
        }
        (Method::PoissonL1, "published", None) => {
            args.l1_preset = L1Preset::Published;
            true
        }
        (Method::PoissonL1, "fast", None) => {
            args.l1_preset = L1Preset::Fast;
            true
        }
        (Method::Filter, "levels", Some(v)) => {
            args.filter_levels = number(key, v)?;
            true
        }
        (Method::Filter, "radius", Some(v)) => {
            args.filter_radius = number(key, v)?;
            true
        }
        (Method::Filter, "enhance", Some(v)) => {
            args.filter_enhance_iterations = number(key, v)?;
            true
        }
        (Method::Filter, "guide", Some(v)) => {
            args.filter_guide = guide(v)?;
            true
        }
        (Method::Filter, "reference", None) => {
            args.filter_enhance_iterations = FilterConfig::reference().enhance_iterations;
            true
        }
        (Method::Filter, "noprefilter", None) => {
            args.filter_no_prefilter = true;
            true
        }
        (Method::GradNet, "nofeat", None) => {
            args.no_features = true;
            true
        }
        (Method::GradNet, "nobias", None) => {
            args.no_bias_correction = true;
            true
        }
        (Method::GradNet, "tile", Some(v)) => {
            args.tile = number(key, v)?;
            true
        }
        _ => false,
    };
    if known {
        Ok(())
    } else {
        Err(format!(
            "unknown option '{option}' for {method}; it takes: {}",
            options_help(method)
        ))
    }
}

/// Parses an option's value.
fn number<T: std::str::FromStr>(key: &str, value: &str) -> Result<T, String> {
    value
        .parse()
        .map_err(|_| format!("option {key}: '{value}' is not a valid number"))
}

/// Parses a filter guide name.
fn guide(value: &str) -> Result<GuideArg, String> {
    match value {
        "rdfc" => Ok(GuideArg::Rdfc),
        "l1" => Ok(GuideArg::L1),
        "none" => Ok(GuideArg::None),
        other => Err(format!(
            "option guide: '{other}' is not one of rdfc, l1, none"
        )),
    }
}
