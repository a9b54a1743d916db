//! Memory bounds (#18): each method's plan-time estimate against the peak heap a counting
//! allocator measures, plans refused by `max_memory_mb` or `ulimit -v` with an error instead
//! of an abort, and executions that fail with `OutOfMemory` (never an abort) wherever one of
//! their large allocations fails.

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::Mutex;

use gdrecon::{Context, ContextOptions, Error, Image, Method, MethodConfig, Plan, Progress};

/// `System`, counting the bytes live now and the most live since the last reset, and failing
/// on request the k-th large allocation ([`LARGE`], [`FAIL_AT`]).
struct Counting;

static CURRENT: AtomicUsize = AtomicUsize::new(0);
static PEAK: AtomicUsize = AtomicUsize::new(0);
/// Allocations of at least this many bytes are counted in [`LARGE_SEEN`] (0: none are).
static LARGE: AtomicUsize = AtomicUsize::new(0);
static LARGE_SEEN: AtomicUsize = AtomicUsize::new(0);
/// The large allocation (counted from 1) that returns null; 0: none.
static FAIL_AT: AtomicUsize = AtomicUsize::new(0);
/// Print where each large allocation comes from (`GDRECON_TRACE_LARGE=1`, to find the ones
/// that abort).
static TRACE: AtomicBool = AtomicBool::new(false);

thread_local! {
    static TRACING: Cell<bool> = const { Cell::new(false) };
}

/// Whether an allocation of `size` bytes must fail (counting it when it is large).
fn refuse(size: usize) -> bool {
    let large = LARGE.load(Ordering::Relaxed);
    if large == 0 || size < large || TRACING.with(Cell::get) {
        return false;
    }
    let k = LARGE_SEEN.fetch_add(1, Ordering::SeqCst) + 1;
    let fail = k == FAIL_AT.load(Ordering::SeqCst);
    if TRACE.load(Ordering::Relaxed) {
        TRACING.with(|t| t.set(true));
        let trace = std::backtrace::Backtrace::force_capture().to_string();
        let ours: Vec<&str> = trace
            .lines()
            .filter(|l| l.contains("gdrecon::") && !l.contains("memory::"))
            .take(4)
            .collect();
        eprintln!(
            "large #{k} ({size} B{}): {}",
            if fail { ", FAILED" } else { "" },
            ours.join(" <- ")
        );
        TRACING.with(|t| t.set(false));
    }
    fail
}

// SAFETY: every call is forwarded to `System` unchanged, or answered with null (an
// allocation failure, which callers must handle); only counters are added.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        if refuse(layout.size()) {
            return std::ptr::null_mut();
        }
        let p = System.alloc(layout);
        if !p.is_null() {
            grow(layout.size());
        }
        p
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        if refuse(layout.size()) {
            return std::ptr::null_mut();
        }
        let p = System.alloc_zeroed(layout);
        if !p.is_null() {
            grow(layout.size());
        }
        p
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        System.dealloc(ptr, layout);
        CURRENT.fetch_sub(layout.size(), Ordering::Relaxed);
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        if new_size > layout.size() && refuse(new_size) {
            return std::ptr::null_mut();
        }
        let p = System.realloc(ptr, layout, new_size);
        if !p.is_null() {
            if new_size > layout.size() {
                grow(new_size - layout.size());
            } else {
                CURRENT.fetch_sub(layout.size() - new_size, Ordering::Relaxed);
            }
        }
        p
    }
}

fn grow(bytes: usize) {
    let now = CURRENT.fetch_add(bytes, Ordering::Relaxed) + bytes;
    PEAK.fetch_max(now, Ordering::Relaxed);
}

#[global_allocator]
static ALLOCATOR: Counting = Counting;

/// One test at a time: the counters are process-wide.
static SERIAL: Mutex<()> = Mutex::new(());

/// Peak heap bytes above what was live before, while `config` is planned for the frame and
/// executed once.
fn measured_peak(config: &MethodConfig, frame: &gdrecon::Frame, context: &Context) -> usize {
    let start = CURRENT.load(Ordering::Relaxed);
    PEAK.store(start, Ordering::Relaxed);
    {
        let mut plan = Plan::new(context, config, frame.width(), frame.height()).unwrap();
        let (image, _) = plan.execute(frame, &Progress::none()).unwrap();
        assert!(image.all_finite());
    }
    PEAK.load(Ordering::Relaxed) - start
}

#[test]
fn estimates_bound_the_measured_peak() {
    let _serial = SERIAL.lock().unwrap_or_else(|p| p.into_inner());
    let (w, h) = (256, 192);
    let frame = gdrecon::synth::synthetic_frame(w, h, 8.0, 7);
    let context = Context::new(ContextOptions::with_threads(Some(2))).unwrap();
    let mut table = String::new();
    for method in [Method::PoissonL2, Method::PoissonL1, Method::Frgr] {
        let config = MethodConfig::default_for(method);
        let estimate = config.memory_estimate(w, h) as usize;
        let peak = measured_peak(&config, &frame, &context);
        table += &format!(
            "{method}: peak {peak} B ({:.1} B/px), estimate {estimate} B ({:.2}x)\n",
            peak as f64 / (w * h) as f64,
            estimate as f64 / peak as f64
        );
        assert!(
            estimate >= peak,
            "{method}: estimate below the peak\n{table}"
        );
        assert!(
            estimate <= 3 * peak,
            "{method}: estimate over 3x the peak\n{table}"
        );
    }
    println!("{table}");
}

#[test]
fn max_memory_mb_refuses_a_plan_naming_both_numbers() {
    let _serial = SERIAL.lock().unwrap_or_else(|p| p.into_inner());
    let context =
        Context::new(ContextOptions::with_threads(Some(1)).with_max_memory_mb(1)).unwrap();
    let config = MethodConfig::default_for(Method::PoissonL1);
    let estimate_mib = config.memory_estimate(1280, 720).div_ceil(1 << 20);
    let err = Plan::new(&context, &config, 1280, 720).unwrap_err();
    let message = err.to_string();
    assert!(matches!(err, Error::OutOfMemory(_)), "{err:?}");
    assert!(
        message.contains(&format!("{estimate_mib} MiB")) && message.contains("max_memory_mb = 1"),
        "{message}"
    );
    assert!(!message.contains('\n'), "{message}");
    // A limit above the estimate plans.
    let context =
        Context::new(ContextOptions::with_threads(Some(1)).with_max_memory_mb(estimate_mib + 1))
            .unwrap();
    Plan::new(&context, &config, 1280, 720).unwrap();
}

#[test]
fn huge_sizes_are_refused_not_aborted() {
    let _serial = SERIAL.lock().unwrap_or_else(|p| p.into_inner());
    // 100000 x 100000 needs over 64 GiB with any method (copy: 112 GiB): refused by the
    // limit; estimates saturate instead of overflowing.
    let context =
        Context::new(ContextOptions::with_threads(Some(1)).with_max_memory_mb(64 << 10)).unwrap();
    for method in Method::ALL {
        let config = MethodConfig::default_for(method);
        assert!(
            config.memory_estimate(100_000, 100_000) > 64 << 30,
            "{method}"
        );
        assert!(
            config.memory_estimate(usize::MAX, usize::MAX) == u64::MAX,
            "{method}"
        );
        let err = Plan::new(&context, &config, 100_000, 100_000).unwrap_err();
        assert!(matches!(err, Error::OutOfMemory(_)), "{method}: {err:?}");
    }
}

#[test]
fn try_zeros_fails_instead_of_aborting() {
    let _serial = SERIAL.lock().unwrap_or_else(|p| p.into_inner());
    let err = gdrecon::Image::try_zeros(3, 1 << 40, 1 << 30).unwrap_err();
    assert!(matches!(err, Error::OutOfMemory(_)), "{err:?}");
    let err = gdrecon::Image::try_zeros(3, usize::MAX, 2).unwrap_err();
    assert!(matches!(err, Error::OutOfMemory(_)), "{err:?}");
    assert_eq!(
        gdrecon::Image::try_zeros(3, 4, 2).unwrap(),
        gdrecon::Image::zeros(3, 4, 2)
    );
}

/// The child of [`address_space_limit_refuses_instead_of_aborting`]: run by it under
/// `ulimit -v`, it plans L1 for 8192 x 8192 (about 7.5 GiB).
#[test]
#[ignore = "run by address_space_limit_refuses_instead_of_aborting under ulimit -v"]
fn l1_8192_under_the_limit() {
    if std::env::var_os("GDRECON_MEMORY_CHILD").is_none() {
        return;
    }
    let context = Context::new(ContextOptions::with_threads(Some(2))).unwrap();
    let config = MethodConfig::default_for(Method::PoissonL1);
    let err = Plan::new(&context, &config, 8192, 8192).unwrap_err();
    assert!(matches!(err, Error::OutOfMemory(_)), "{err:?}");
    println!("REFUSED: {err}");
}

#[cfg(target_os = "linux")]
#[test]
fn address_space_limit_refuses_instead_of_aborting() {
    let _serial = SERIAL.lock().unwrap_or_else(|p| p.into_inner());
    let exe = std::env::current_exe().unwrap();
    let out = std::process::Command::new("bash")
        .arg("-c")
        .arg("ulimit -v 3000000; exec \"$0\" l1_8192_under_the_limit --exact --ignored --nocapture --test-threads 1")
        .arg(&exe)
        .env("GDRECON_MEMORY_CHILD", "1")
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        out.status.success()
            && stdout.contains("REFUSED: out of memory: method l1 for 8192 x 8192"),
        "status {:?}\n{stdout}\n{stderr}",
        out.status
    );
}

/// The table next to the coefficients: peak heap against the estimate at two frame sizes
/// (`cargo test --release --test memory -- --ignored --nocapture peak_table`).
#[test]
#[ignore = "prints the measurements; slower"]
fn peak_table() {
    let _serial = SERIAL.lock().unwrap_or_else(|p| p.into_inner());
    let context = Context::new(ContextOptions::with_threads(Some(2))).unwrap();
    for (w, h) in [(640, 360), (1280, 720)] {
        let frame = gdrecon::synth::synthetic_frame(w, h, 8.0, 7);
        for (method, preset, params) in [
            (Method::PoissonL2, None, ""),
            (Method::PoissonL1, None, ""),
            (Method::PoissonL1, Some("published"), ""),
            (Method::Frgr, None, ""),
            (Method::Frgr, Some("reference"), ""),
            (Method::Frgr, Some("fast"), ""),
            (Method::Frgr, None, "guide=l1"),
            (Method::Frgr, None, "levels=1"),
        ] {
            let mut config = match preset {
                Some(p) => MethodConfig::preset(method, p).unwrap(),
                None => MethodConfig::default_for(method),
            };
            if !params.is_empty() {
                config.set_assignment(params).unwrap();
            }
            let estimate = config.memory_estimate(w, h);
            let peak = measured_peak(&config, &frame, &context);
            println!(
                "| {method} {} {params} | {w} x {h} | {:.1} MiB | {:.1} B/px | {:.1} MiB | {:.2}x |",
                preset.unwrap_or(""),
                peak as f64 / 1048576.0,
                peak as f64 / (w * h) as f64,
                estimate as f64 / 1048576.0,
                estimate as f64 / peak as f64
            );
        }
    }
}

/// Executes `plan` with the `fail_at`-th allocation of at least `large` bytes failing (0: none
/// fails); returns the result and how many large allocations there were.
fn execute_failing(
    plan: &mut Plan,
    frame: &gdrecon::Frame,
    out: &mut Image,
    large: usize,
    fail_at: usize,
) -> (gdrecon::Result<String>, usize) {
    LARGE_SEEN.store(0, Ordering::SeqCst);
    FAIL_AT.store(fail_at, Ordering::SeqCst);
    LARGE.store(large, Ordering::SeqCst);
    let result = plan
        .execute_into(frame, out, &Progress::none())
        .map(|report| report.method);
    LARGE.store(0, Ordering::SeqCst);
    FAIL_AT.store(0, Ordering::SeqCst);
    (result, LARGE_SEEN.load(Ordering::SeqCst))
}

/// Every large allocation an execution makes (here: 16 KiB or more, a third of one plane of
/// the 128 x 96 frame; row buffers stay below it) fails in turn, on a fresh plan (allocations
/// made by the first frame count) and on one that ran before: each time the execution
/// returns `OutOfMemory`, never aborts the process, and the plan then gives the image of a
/// plan that never failed. (ONNX Runtime's and OIDN's own allocations are theirs, not
/// counted here.)
#[test]
fn an_execution_whose_allocation_fails_returns_out_of_memory() {
    let _serial = SERIAL.lock().unwrap_or_else(|p| p.into_inner());
    TRACE.store(
        std::env::var_os("GDRECON_TRACE_LARGE").is_some(),
        Ordering::Relaxed,
    );
    let (w, h) = (128, 96);
    let large = 16 << 10;
    let frame = gdrecon::synth::synthetic_frame(w, h, 4.0, 5);
    let context = Context::new(ContextOptions::with_threads(Some(2))).unwrap();
    let mut table = String::new();
    for method in Method::ALL.into_iter().filter(|m| m.is_built()) {
        let config = MethodConfig::default_for(method);
        let mut want = Image::zeros(3, w, h);
        // What the context loads once (ONNX Runtime, OIDN, the search for them) is loaded
        // here, on a plan of its own, so that every fresh plan below counts the same.
        Plan::new(&context, &config, w, h)
            .unwrap()
            .execute_into(&frame, &mut want, &Progress::none())
            .unwrap();
        let mut plan = Plan::new(&context, &config, w, h).unwrap();
        let (first, count_first) = execute_failing(&mut plan, &frame, &mut want, large, 0);
        let path = first.unwrap();
        let (_, count_later) = execute_failing(&mut plan, &frame, &mut want.clone(), large, 0);
        // `GDRECON_TRACE_LARGE=census`: only list where the large allocations come from.
        let census = std::env::var_os("GDRECON_TRACE_LARGE").is_some_and(|v| v == "census");
        for (fresh, count) in [(true, count_first), (false, count_later)] {
            if census {
                break;
            }
            for k in 1..=count {
                let mut plan_k;
                let plan = if fresh {
                    plan_k = Plan::new(&context, &config, w, h).unwrap();
                    &mut plan_k
                } else {
                    &mut plan
                };
                let mut out = Image::zeros(3, w, h);
                match execute_failing(plan, &frame, &mut out, large, k).0 {
                    Err(Error::OutOfMemory(m)) => {
                        assert!(!m.contains('\n'), "{method}: {m}")
                    }
                    Ok(_) => panic!("{method}: large allocation {k} failed, and it went on"),
                    Err(e) => panic!("{method}: large allocation {k}: {e:?}"),
                }
                plan.execute_into(&frame, &mut out, &Progress::none())
                    .unwrap();
                assert!(
                    out == want,
                    "{method}: after a failed allocation {k}, another image"
                );
            }
        }
        table.push_str(&format!(
            "{method} (ran {path}): {count_first} large allocations on the first frame, \
             {count_later} later\n"
        ));
    }
    print!("{table}");
}

/// `max_memory_mb` sizes tiles (`MethodConfig::fitted_to`, what `Plan::new` plans): for every
/// method, size and limit, the fitted estimate is within the limit or at the method's least
/// (its estimate under a limit of 0), never above the unfitted estimate, and a limit the
/// estimate already fits changes nothing.
#[test]
fn a_memory_limit_fits_the_estimate_or_leaves_it_at_its_least() {
    const MIB: u64 = 1 << 20;
    for method in Method::ALL {
        let config = MethodConfig::default_for(method);
        for (w, h) in [(320, 180), (1920, 1080), (3840, 2160)] {
            let full = config.memory_estimate(w, h);
            assert_eq!(config.fitted_to(w, h, full), config, "{method} {w} x {h}");
            let least = config.fitted_to(w, h, 0).memory_estimate(w, h);
            assert!(least <= full, "{method} {w} x {h}");
            let mut previous = least;
            for step in 0..=16 {
                let limit = least.saturating_sub(MIB) + (full - least + MIB) * step / 16;
                let fitted = config.fitted_to(w, h, limit).memory_estimate(w, h);
                assert!(
                    fitted <= limit.max(least) && fitted <= full && fitted >= previous,
                    "{method} {w} x {h}: limit {limit}, fitted {fitted}, least {least}, full {full}"
                );
                previous = fitted;
            }
        }
    }
    // The combiner's network tiles go no lower than four margins a side (96 x 96), even
    // under a limit of 0; a budget set lower by hand stays.
    let fitted = |config: MethodConfig| match config.fitted_to(3840, 2160, 0) {
        MethodConfig::Combiner(c) => c.tile_pixels,
        other => panic!("{other:?}"),
    };
    assert_eq!(fitted(MethodConfig::default_for(Method::Combiner)), 96 * 96);
    let mut small = gdrecon::recon::CombinerConfig::default();
    small.tile_pixels = 56 * 56;
    assert_eq!(fitted(MethodConfig::Combiner(small)), 56 * 56);
    // The methods that tile have room to fit at 4K.
    for method in [
        Method::GradNet,
        Method::Combiner,
        Method::Prior,
        Method::Auto,
    ] {
        let config = MethodConfig::default_for(method);
        let least = config.fitted_to(3840, 2160, 0).memory_estimate(3840, 2160);
        let full = config.memory_estimate(3840, 2160);
        println!(
            "{method} at 3840 x 2160: least {} MiB, unfitted {} MiB",
            least / MIB,
            full / MIB
        );
        assert!(
            least + 192 * MIB < full,
            "{method}: least {} MiB, full {} MiB",
            least / MIB,
            full / MIB
        );
    }
}

#[test]
fn a_plan_over_the_limit_is_fitted_and_refused_only_under_its_least() {
    let _serial = SERIAL.lock().unwrap_or_else(|p| p.into_inner());
    const MIB: u64 = 1 << 20;
    let (w, h) = (1920, 1080);
    // The prior needs no library to plan; OIDN's scratch is what a limit lowers.
    let config = MethodConfig::default_for(Method::Prior);
    let full = config.memory_estimate(w, h).div_ceil(MIB);
    let least = config
        .fitted_to(w, h, 0)
        .memory_estimate(w, h)
        .div_ceil(MIB);
    assert!(least < full, "{least} {full}");
    let plan = |mb: u64| {
        let context =
            Context::new(ContextOptions::with_threads(Some(1)).with_max_memory_mb(mb)).unwrap();
        Plan::new(&context, &config, w, h)
    };
    plan(least).unwrap();
    let err = plan(least - 1).unwrap_err();
    assert!(
        matches!(err, Error::OutOfMemory(_))
            && err
                .to_string()
                .contains(&format!("needs about {least} MiB"))
            && err
                .to_string()
                .contains(&format!("max_memory_mb = {}", least - 1)),
        "{err}"
    );
}
