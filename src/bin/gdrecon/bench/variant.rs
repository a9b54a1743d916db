//! Named method variants: `METHOD[:OPTION[:OPTION...]]`, e.g. `l1:reweight_steps=5`,
//! `l1:published` or `frgr:guide=l1:levels=1`.
//!
//! An option is a parameter of the method, `NAME=VALUE`, or one of its presets; both come
//! from the method's parameter table (`gdrecon params` lists them), so a new parameter or
//! method needs nothing here.

use gdrecon::{Method, MethodConfig};

use crate::RuntimeArgs;

/// One method at one group of settings, as timed and reported by `bench`.
#[derive(Clone, Debug)]
pub struct Variant {
    /// The method's CLI name (`l2`, `l1`, `frgr`, `gradnet`).
    pub method: String,
    /// The options after the method name (`reweight_steps=5`), or `default`.
    pub setting: String,
    /// The library configuration the variant runs.
    pub config: MethodConfig,
}

impl Variant {
    /// The variant's name as given on the command line: `l1`, `l1:reweight_steps=5`.
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

/// The variant names for `--methods` (each at its default settings, or its sweep).
pub fn names_for_methods(methods: &str, sweep: bool) -> gdrecon::Result<Vec<String>> {
    let mut names = Vec::new();
    for m in split_list(methods) {
        let method: Method = m.parse()?;
        if sweep {
            names.extend(method.sweep().iter().map(|options| {
                if options.is_empty() {
                    method.name().to_owned()
                } else {
                    format!("{method}:{options}")
                }
            }));
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

/// Parses a variant name. `common` are `NAME=VALUE` settings for every variant whose method
/// has that parameter (the variant's own options override them); `runtime` says where ONNX
/// Runtime is and which model file every `gradnet` and `combiner` variant runs.
pub fn parse(name: &str, common: &[String], runtime: &RuntimeArgs) -> gdrecon::Result<Variant> {
    let mut parts = name.split(':').map(str::trim);
    let method: Method = parts
        .next()
        .unwrap_or_default()
        .parse()
        .map_err(|e| bad(name, &message(e)))?;
    let options: Vec<&str> = parts.collect();
    let mut config = MethodConfig::default_for(method);
    for (i, option) in options.iter().enumerate() {
        if !option.contains('=') {
            if i > 0 {
                return Err(bad(
                    name,
                    &format!("preset '{option}' replaces every setting: name it first"),
                ));
            }
            config = MethodConfig::preset(method, option).map_err(|e| bad(name, &message(e)))?;
        }
    }
    for assignment in common {
        if config.param(param_name(assignment)).is_ok() {
            config
                .set_assignment(assignment)
                .map_err(|e| bad(name, &message(e)))?;
        }
    }
    for option in options.iter().filter(|o| o.contains('=')) {
        config
            .set_assignment(option)
            .map_err(|e| bad(name, &message(e)))?;
    }
    runtime.apply(&mut config);
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

/// Checks that each of `common` names a parameter of at least one variant's method.
pub fn check_common(common: &[String], variants: &[Variant]) -> gdrecon::Result<()> {
    for assignment in common {
        let param = param_name(assignment);
        if !variants.iter().any(|v| v.config.param(param).is_ok()) {
            let methods: Vec<&str> = variants.iter().map(|v| v.method.as_str()).collect();
            return Err(gdrecon::Error::InvalidArgument(format!(
                "--param {assignment}: none of the methods timed ({}) has a parameter '{param}' \
                 (`gdrecon params` lists them)",
                methods.join(", ")
            )));
        }
    }
    Ok(())
}

/// The `NAME` of a `NAME=VALUE` setting.
fn param_name(assignment: &str) -> &str {
    assignment.split('=').next().unwrap_or_default().trim()
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
