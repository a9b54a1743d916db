//! The CPU a benchmark ran on, named well enough to compare runs: the model name alone is not
//! (two machines both called "AMD EPYC" here differed 2.6x in GradNet's time against OIDN: one
//! had AVX-512 VNNI, the other AVX2 only), so the vector instruction sets that the kernels,
//! ONNX Runtime and OIDN pick at run time are named beside it, and so is the x86 family and
//! model, which tell microarchitectures with the same name and the same instructions apart (an
//! AVX2 EPYC of family 23 model 1, Zen 1, runs 256-bit vectors as two 128-bit halves).

/// `MODEL[, family F model M] (SIMD)`, e.g. `AMD EPYC, family 25 model 17 (AVX-512 VNNI BF16)`,
/// `Intel(R) Xeon(R) Processor, family 6 model 143 (AVX-512 VNNI BF16 AMX)` or `AMD EPYC,
/// family 23 model 1 (AVX2 FMA)`.
pub fn describe() -> String {
    format!("{} ({})", model(), simd())
}

/// The value of the first line of /proc/cpuinfo (Linux) whose key is `key`.
fn cpuinfo(key: &str) -> Option<String> {
    let text = std::fs::read_to_string("/proc/cpuinfo").ok()?;
    text.lines().find_map(|l| {
        let (k, v) = l.split_once(':')?;
        (k.trim() == key).then(|| v.trim().to_owned())
    })
}

/// The CPU's model name, with its family and model numbers where the kernel gives them
/// (Linux), or `unknown CPU`.
fn model() -> String {
    let name = cpuinfo("model name").unwrap_or_else(|| "unknown CPU".to_owned());
    match (cpuinfo("cpu family"), cpuinfo("model")) {
        (Some(family), Some(model)) => format!("{name}, family {family} model {model}"),
        _ => name,
    }
}

/// The widest vector tier the multiversioned kernels run (`x86_64+avx512f+avx512bw+avx512vl`,
/// `x86_64+avx2+fma`, or the baseline), then the extensions ONNX Runtime's int8 and bf16 paths
/// use (VNNI: GradNet's int8 graph is ~3x faster with it than without).
fn simd() -> String {
    #[cfg(target_arch = "x86_64")]
    {
        let mut parts: Vec<&str> = Vec::new();
        let avx512 = std::arch::is_x86_feature_detected!("avx512f")
            && std::arch::is_x86_feature_detected!("avx512bw")
            && std::arch::is_x86_feature_detected!("avx512vl");
        if avx512 {
            parts.push("AVX-512");
            if std::arch::is_x86_feature_detected!("avx512vnni") {
                parts.push("VNNI");
            }
            if std::arch::is_x86_feature_detected!("avx512bf16") {
                parts.push("BF16");
            }
            // Intel's matrix tiles: ONNX Runtime's int8 GEMMs can use them, and OIDN runs
            // relatively faster on such a Xeon (docs/benchmarks.md, forty-seventh session).
            // Read from the kernel's flags: `is_x86_feature_detected!("amx-int8")` is unstable.
            let flags = cpuinfo("flags").unwrap_or_default();
            if flags.split_whitespace().any(|f| f == "amx_int8") {
                parts.push("AMX");
            }
        } else if std::arch::is_x86_feature_detected!("avx2")
            && std::arch::is_x86_feature_detected!("fma")
        {
            parts.push("AVX2 FMA");
            if std::arch::is_x86_feature_detected!("avxvnni") {
                parts.push("AVX-VNNI");
            }
        } else {
            parts.push("no AVX2: baseline kernels");
        }
        parts.join(" ")
    }
    #[cfg(target_arch = "aarch64")]
    {
        "NEON".to_owned()
    }
    #[cfg(not(any(target_arch = "x86_64", target_arch = "aarch64")))]
    {
        "baseline kernels".to_owned()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_the_model_and_a_vector_tier() {
        let d = describe();
        let (model, simd) = d.split_once(" (").expect("MODEL (SIMD)");
        assert!(!model.is_empty(), "{d}");
        assert!(simd.ends_with(')') && simd.len() > 1, "{d}");
    }
}
