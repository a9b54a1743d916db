//! Parameters from C: the typed setters and getters of `gdr_filter` and the listing
//! (`gdr_method_param_count`, `gdr_method_param`), all read from the methods' parameter tables
//! ([`crate::recon::param`]) plus the two every filter has, `spp` and `strict`.

use std::ffi::{c_char, CString};
use std::sync::OnceLock;

use super::gdr_error::*;
use super::{c_str, err, gdr_error, guard, out_ptr, CResult};
use crate::recon::param::{Kind, ParamInfo, Range, Value};
use crate::recon::Method;

/// The kind of a parameter, and which `gdr_filter_set_*` / `gdr_filter_get_*` pair it takes.
#[repr(u32)]
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum gdr_param_kind {
    /// A float: `gdr_filter_set_float`.
    GDR_PARAM_FLOAT = 0,
    /// An integer: `gdr_filter_set_int`.
    GDR_PARAM_INT = 1,
    /// A boolean: `gdr_filter_set_bool`.
    GDR_PARAM_BOOL = 2,
    /// One of the names in `choices`, set by its index with `gdr_filter_set_int`.
    GDR_PARAM_CHOICE = 3,
}

/// One parameter of a method, as `gdr_method_param` describes it; its strings are static.
///
/// The one struct that crosses the ABI, versioned by its first field: set `size` to
/// `sizeof(gdr_param_info)` before the call. Later versions only append fields and fill no more
/// than `size` bytes, so a program built against this header keeps working.
#[repr(C)]
#[derive(Clone, Copy, Debug)]
pub struct gdr_param_info {
    /// Set by the caller: `sizeof(gdr_param_info)`.
    pub size: usize,
    /// The name the setters take.
    pub name: *const c_char,
    /// Its kind: which setter it takes.
    pub kind: gdr_param_kind,
    /// Lowest accepted value (a choice: 0; a bool: 0).
    pub min: f64,
    /// Highest accepted value (a choice: the last index; a bool: 1).
    pub max: f64,
    /// `min` itself is not accepted.
    pub min_exclusive: bool,
    /// `max` itself is not accepted.
    pub max_exclusive: bool,
    /// The default (a bool as 0 or 1, a choice as its index).
    pub default_value: f64,
    /// A choice's names by index, separated by commas (`"rdfc,l1,none"`); `""` otherwise.
    pub choices: *const c_char,
    /// One line: what it does.
    pub doc: *const c_char,
}

// SAFETY: the pointers are to static, immutable strings.
unsafe impl Send for gdr_param_info {}
unsafe impl Sync for gdr_param_info {}

/// Which `gdr_filter_set_*` function was called.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Setter {
    Float,
    Int,
    Bool,
}

impl Setter {
    fn name(self) -> &'static str {
        match self {
            Setter::Float => "float",
            Setter::Int => "int",
            Setter::Bool => "bool",
        }
    }

    fn of(kind: Kind) -> Setter {
        match kind {
            Kind::Float => Setter::Float,
            Kind::Int | Kind::Choice => Setter::Int,
            Kind::Bool => Setter::Bool,
        }
    }
}

/// The parameters every filter has, whatever its method.
pub(crate) fn frame_params() -> [ParamInfo; 2] {
    [
        ParamInfo {
            name: "spp".to_owned(),
            kind: Kind::Float,
            range: Range::closed(0.0, f64::from(f32::MAX)),
            choices: &[],
            default: Value::Float(0.0),
            doc: "Samples per pixel of the base image; 0 = unknown (frgr needs it)",
        },
        ParamInfo {
            name: "strict".to_owned(),
            kind: Kind::Bool,
            range: Range::closed(0.0, 1.0),
            choices: &[],
            default: Value::Bool(false),
            doc: "Refuse NaN, Inf or negative colour (GDR_ERROR_INVALID_INPUT) instead of \
                  replacing them",
        },
    ]
}

/// The parameters of a filter running `method`: the method's, then `spp` and `strict`.
pub(crate) fn filter_params(method: Method) -> Vec<ParamInfo> {
    let mut all = method.params();
    all.extend(frame_params());
    all
}

/// Finds `name` among `method`'s parameters and checks that `setter` is the one it takes.
pub(crate) fn lookup(method: Method, name: &str, setter: Setter) -> CResult<ParamInfo> {
    let all = filter_params(method);
    let Some(info) = all.iter().find(|i| i.name == name) else {
        let list: Vec<String> = all
            .iter()
            .map(|i| format!("{} ({})", i.name, i.kind))
            .collect();
        return err(
            GDR_ERROR_INVALID_ARGUMENT,
            format!(
                "unknown parameter '{name}' for method '{method}', expected one of: {}",
                list.join(", ")
            ),
        );
    };
    let wanted = Setter::of(info.kind);
    if wanted != setter {
        return err(
            GDR_ERROR_INVALID_ARGUMENT,
            format!(
                "parameter '{name}' of method '{method}' is a {}: use gdr_filter_set_{1} / gdr_filter_get_{1}",
                info.kind,
                wanted.name()
            ),
        );
    }
    Ok(info.clone())
}

/// One method's listing with C strings, built once.
struct Listing {
    infos: Vec<gdr_param_info>,
    _strings: Vec<CString>,
}

fn listing(method: Method) -> &'static Listing {
    static ALL: OnceLock<Vec<Listing>> = OnceLock::new();
    let all = ALL.get_or_init(|| Method::ALL.iter().map(|&m| build(m)).collect());
    let index = Method::ALL
        .iter()
        .position(|&m| m == method)
        .expect("every method is listed");
    &all[index]
}

fn build(method: Method) -> Listing {
    let mut strings = Vec::new();
    let mut keep = |s: &str| {
        let c = CString::new(s.replace('\0', " ")).unwrap_or_default();
        // The CString's heap buffer does not move when the CString itself is moved.
        let ptr = c.as_ptr();
        strings.push(c);
        ptr
    };
    let infos = filter_params(method)
        .iter()
        .map(|p| gdr_param_info {
            size: std::mem::size_of::<gdr_param_info>(),
            name: keep(&p.name),
            kind: match p.kind {
                Kind::Float => gdr_param_kind::GDR_PARAM_FLOAT,
                Kind::Int => gdr_param_kind::GDR_PARAM_INT,
                Kind::Bool => gdr_param_kind::GDR_PARAM_BOOL,
                Kind::Choice => gdr_param_kind::GDR_PARAM_CHOICE,
            },
            min: p.range.min,
            max: p.range.max,
            min_exclusive: p.range.min_open,
            max_exclusive: p.range.max_open,
            default_value: match p.default {
                Value::Float(v) => f64::from(v),
                Value::Int(i) => i as f64,
                Value::Bool(b) => f64::from(u8::from(b)),
            },
            choices: keep(&p.choices.join(",")),
            doc: keep(p.doc),
        })
        .collect();
    Listing {
        infos,
        _strings: strings,
    }
}

/// Write into `*count` how many parameters a filter running `method` takes (the method's own, then `"spp"` and `"strict"`).
#[no_mangle]
pub unsafe extern "C" fn gdr_method_param_count(
    method: *const c_char,
    count: *mut usize,
) -> gdr_error {
    guard("gdr_method_param_count", || {
        let count = out_ptr(count, "count")?;
        let method: Method = c_str(method, "method")?.parse()?;
        *count = listing(method).infos.len();
        Ok(())
    })
}

/// Describe parameter `index` (0 to count - 1) of `method` in `*info` (whose `size` the caller sets to `sizeof(gdr_param_info)`): name, kind, range, default, choices, documentation; its strings are static.
#[no_mangle]
pub unsafe extern "C" fn gdr_method_param(
    method: *const c_char,
    index: usize,
    info: *mut gdr_param_info,
) -> gdr_error {
    guard("gdr_method_param", || {
        let info = out_ptr(info, "info")?;
        let ours = std::mem::size_of::<gdr_param_info>();
        if info.size < ours {
            return err(
                GDR_ERROR_INVALID_ARGUMENT,
                format!(
                    "info->size is {}, expected sizeof(gdr_param_info) = {ours}: set it before the call",
                    info.size
                ),
            );
        }
        let method: Method = c_str(method, "method")?.parse()?;
        let infos = &listing(method).infos;
        match infos.get(index) {
            Some(i) => {
                // A larger `size` is a newer header's struct: its extra fields are left alone.
                let size = info.size;
                *info = gdr_param_info { size, ..*i };
                Ok(())
            }
            None => err(
                GDR_ERROR_INVALID_ARGUMENT,
                format!(
                    "parameter index {index} is out of range: method '{method}' has {}",
                    infos.len()
                ),
            ),
        }
    })
}
