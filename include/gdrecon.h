/*
 * gdrecon: reconstruction of gradient-domain Monte Carlo renders, C API.
 *
 * Typical use (OIDN-like; see examples/c/):
 *
 *   gdr_context* ctx; gdr_context_new(&ctx);
 *   gdr_context_set_int(ctx, "threads", 4);      (0 or unset: all cores)
 *   gdr_context_commit(ctx);
 *   gdr_filter* f; gdr_filter_new(ctx, "l1", &f);
 *   gdr_filter_set_float(f, "alpha", 0.2f);
 *   gdr_filter_set_image(f, "color", rgba, w, h, 3, 16, 0);   (RGB read out of RGBA)
 *   gdr_filter_set_image(f, "dx", dx, w, h, 3, 0, 0);         (0 strides: packed)
 *   gdr_filter_set_image(f, "dy", dy, w, h, 3, 0, 0);
 *   gdr_filter_set_image(f, "output", rgba, w, h, 3, 16, 0);  (in place is allowed)
 *   gdr_filter_commit(f);                      (validate + plan, once per size)
 *   gdr_filter_execute(f);                     (per frame; blocking)
 *   gdr_filter_release(&f); gdr_context_release(&ctx);
 *
 * Conventions: row-major images, y down; dx(x,y) = I(x+1,y) - I(x,y), dy(x,y) = I(x,y+1) - I(x,y)
 * (the last column of dx and the last row of dy are ignored); linear HDR f32 RGB; variance is
 * the variance of the colour mean. NaN, Inf and negative colour/variance are replaced by 0 and
 * counted (the report says how many), or rejected with "strict" = true. The output never
 * contains NaN, Inf or negative values.
 *
 * The prior (the product's main path). The optional image "prior" (RGB) is a denoiser's output
 * for this frame, computed from "color" as rendered (not from any average of shifted
 * estimates). The prior paths use it as given: method "auto", method "prior" (the prior alone),
 * l1 with gdr_filter_set_preset(f, "prior") (or "data" = GDR_DATA_PRIOR, weight "prior_alpha"),
 * l2 likewise, frgr with "guide" = GDR_FRGR_GUIDE_PRIOR. Without it they compute it with Intel
 * Open Image Denoise 2, loaded at run time (never linked) from the context string "oidn_path",
 * else OIDN_DYLIB_PATH, a libOpenImageDenoise.so* next to libgdrecon, the project's Python
 * environment; when none loads, gdr_filter_execute fails with GDR_ERROR_UNSUPPORTED and a message
 * listing where it looked. Other methods never load it.
 *
 * Handles. gdr_context and gdr_filter are reference counted: *_retain adds a reference,
 * *_release(&h) drops one and sets h to NULL (releasing NULL is a no-op). A filter keeps its
 * context alive. gdr_frame is owned by its creator and freed by gdr_frame_release(&frame).
 * Parameters are set by name with typed setters; unknown names, wrong types and values out of
 * range are errors (GDR_ERROR_INVALID_ARGUMENT) whose message lists the valid names or states
 * the range. gdr_method_param_count and gdr_method_param list a method's parameters with
 * their kinds, ranges, defaults and documentation (docs/PARAMETERS.md is the same table).
 * Setters and set_image take effect at the next gdr_filter_commit: gdr_filter_execute on a
 * filter changed since its last commit fails with GDR_ERROR_INVALID_OPERATION. Commit again
 * after changing pointers: it re-plans only when the method settings or the size changed.
 *
 * Images are borrowed, never copied by the caller: `ptr`, width, height, channels and byte
 * strides (0 = packed), interleaved (gdr_filter_set_image) or planar
 * (gdr_filter_set_image_planar). Pointers and strides must be multiples of 4 bytes, and a view
 * must not overlap itself. The memory must stay valid from set_image until the last execute
 * that uses it returns. The output may be exactly one of the input views (same pointer,
 * strides and size: in place), since every input is read before the output is written; an
 * output that otherwise shares memory with an input is GDR_ERROR_OVERLAP (views that merely
 * interleave in one buffer without sharing elements are fine).
 *
 * Errors. Every fallible function returns a gdr_error status (GDR_ERROR_NONE = 0 is success)
 * and, on failure, records a message for the calling thread: gdr_get_error(&msg) returns the
 * last failure's code and message (naming the function, the image or parameter, and the
 * problem) and clears it. Each failure kind has its own code: NULL pointers
 * GDR_ERROR_NULL_POINTER, wrong sizes / strides / channels GDR_ERROR_INVALID_IMAGE, overlapping
 * output GDR_ERROR_OVERLAP, calls in the wrong order GDR_ERROR_INVALID_OPERATION. Functions
 * that create an object set *out to NULL on failure. No panic or exception crosses the
 * boundary: an internal bug becomes GDR_ERROR_UNKNOWN. GDR_ERROR_CANCELLED is the answer to a
 * cancellation, not a failure of the library. Every failure of a function given a context or
 * a filter is also sent to that context's log callback at GDR_LOG_ERROR (a cancellation at
 * GDR_LOG_INFO). The library never prints and never exits the process: the first
 * gdr_context_new installs a panic hook that keeps panics on the library's threads (inside a
 * gdr_ call, or in a context's pool) off stderr, their message going to gdr_get_error and the
 * log callback; panics elsewhere go to the hook installed before it, so a Rust host's own hook
 * keeps working (one installed later replaces gdrecon's for the whole process).
 *
 * Threads. The library runs on its context's own pool (never pinned). All functions may be
 * called from any thread. A gdr_context may be shared by threads and filters freely. A
 * gdr_filter may be used from any thread, but calls on one filter must not overlap: a call
 * made while another call on the same filter runs (e.g. from its progress callback) fails
 * with GDR_ERROR_INVALID_OPERATION instead of blocking, except gdr_filter_cancel (any thread,
 * any time) and retain/release. Different filters may execute concurrently. A gdr_frame is
 * immutable and may be read from several threads. Do not release a handle while another thread
 * still uses it; a callback may release the handle it runs for (the running call holds its own
 * reference until it returns). Callbacks run on library threads; user pointers are passed back
 * untouched. Callbacks must not throw or longjmp. The log callback is called for one context
 * by one thread at a time (a lock is held while it runs); replacing or removing it waits for a
 * running call, after which the old one is never called again. It may call gdr_ functions,
 * except gdr_context_set_log_callback on its own context (GDR_ERROR_INVALID_OPERATION); what
 * they would log on that context is dropped.
 *
 * fork(). A context's pool threads are not copied into a child process: in a child forked
 * after gdr_context_commit, the context and its filters cannot run (gdr_filter_new,
 * gdr_filter_commit and gdr_filter_execute return GDR_ERROR_INVALID_OPERATION, naming the
 * fork, instead of waiting forever); they may only be released. Create and commit a new
 * context in the child (or fork before committing, or exec).
 *
 * ABI evolution. Objects are opaque and configured by string-keyed setters, so new
 * parameters, images and methods never change the ABI. One struct crosses it, gdr_param_info
 * (filled by gdr_method_param), versioned by its leading size field: fields are only appended. Enums are passed as uint32_t and validated. Within a major version (the soname
 * libgdrecon.so.MAJOR), functions are only added, never changed or removed; check
 * gdr_version() >= GDR_VERSION at run time to detect a header newer than the library.
 */


#ifndef GDRECON_H
#define GDRECON_H

/* Generated by cbindgen from src/capi/ (see cbindgen.toml): do not edit by hand. */

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

// Major version of the library; matches `Cargo.toml`.
#define GDR_VERSION_MAJOR 0

// Minor version of the library; matches `Cargo.toml`.
#define GDR_VERSION_MINOR 1

// Patch version of the library; matches `Cargo.toml`.
#define GDR_VERSION_PATCH 0

// The version as one number, `MAJOR * 10000 + MINOR * 100 + PATCH` (what `gdr_version` returns).
#define GDR_VERSION 100

// Filter `"guide"`: RDFC's first pass, as the authors' release (the default).
#define GDR_FRGR_GUIDE_RDFC 0

// Filter `"guide"`: the screened Poisson L1 reconstruction.
#define GDR_FRGR_GUIDE_L1 1

// Filter `"guide"`: no pre-denoiser, the noisy colour itself (an ablation).
#define GDR_FRGR_GUIDE_NONE 2

// Filter `"guide"`: the prior (image `"prior"` if set, else Open Image Denoise on `"color"`).
#define GDR_FRGR_GUIDE_PRIOR 3

// Screened Poisson `"data"`: the data term is the base image `"color"` (the default).
#define GDR_DATA_COLOR 0

// Screened Poisson `"data"`: the data term is the prior, weighted by `"prior_alpha"`.
#define GDR_DATA_PRIOR 1

// Status codes returned by every fallible function (`GDR_ERROR_NONE` is success).
enum gdr_error
#ifdef __cplusplus
  : uint32_t
#endif // __cplusplus
 {
    // Success.
    GDR_ERROR_NONE = 0,
    // An internal error, e.g. a bug caught at the boundary (the message says where).
    GDR_ERROR_UNKNOWN = 1,
    // A parameter value is out of range, a name is unknown, a type or enum value is wrong.
    GDR_ERROR_INVALID_ARGUMENT = 2,
    // A call in the wrong order or on a busy object: execute before commit, commit without
    // a required image, a setter on a committed context, a call on a filter while another
    // call on it runs.
    GDR_ERROR_INVALID_OPERATION = 3,
    // An allocation size that cannot be represented.
    GDR_ERROR_OUT_OF_MEMORY = 4,
    // Valid, but this build or machine cannot do it (threads refused, method not built).
    GDR_ERROR_UNSUPPORTED = 5,
    // The progress callback returned false or `gdr_filter_cancel` was called.
    GDR_ERROR_CANCELLED = 6,
    // A file could not be read or is not a valid frame bundle.
    GDR_ERROR_IO = 7,
    // The frame's values are unusable (strict mode: NaN, Inf or negative colour).
    GDR_ERROR_INVALID_INPUT = 8,
    // A required pointer argument is NULL.
    GDR_ERROR_NULL_POINTER = 9,
    // An image view is unusable: zero or mismatched size, wrong channel count, a stride that
    // is not a multiple of 4 or makes elements overlap, a pointer not aligned to 4 bytes.
    GDR_ERROR_INVALID_IMAGE = 10,
    // The output view shares memory with an input view without being the same view.
    GDR_ERROR_OVERLAP = 11,
    // The GradNet model file is damaged, not the exported one (SHA-256 mismatch) or rejected
    // by ONNX Runtime.
    GDR_ERROR_INVALID_MODEL = 12,
    // A library loaded at run time failed while running: ONNX Runtime (configuring a session,
    // running the network) or Open Image Denoise (computing a prior).
    GDR_ERROR_RUNTIME = 13,
};
#ifndef __cplusplus
typedef uint32_t gdr_error;
#endif // __cplusplus

// The kind of a parameter, and which `gdr_filter_set_*` / `gdr_filter_get_*` pair it takes.
enum gdr_param_kind
#ifdef __cplusplus
  : uint32_t
#endif // __cplusplus
 {
    // A float: `gdr_filter_set_float`.
    GDR_PARAM_FLOAT = 0,
    // An integer: `gdr_filter_set_int`.
    GDR_PARAM_INT = 1,
    // A boolean: `gdr_filter_set_bool`.
    GDR_PARAM_BOOL = 2,
    // One of the names in `choices`, set by its index with `gdr_filter_set_int`.
    GDR_PARAM_CHOICE = 3,
};
#ifndef __cplusplus
typedef uint32_t gdr_param_kind;
#endif // __cplusplus

// Log levels for the context's log callback (`log_level` parameter).
enum gdr_log_level
#ifdef __cplusplus
  : uint32_t
#endif // __cplusplus
 {
    // Nothing is logged.
    GDR_LOG_NONE = 0,
    // Failed calls (a cancellation is logged at `GDR_LOG_INFO`: it is not a failure).
    GDR_LOG_ERROR = 1,
    // Replaced input values and other suspicious input (the default level).
    GDR_LOG_WARNING = 2,
    // One report per execution: method, stage times, notes; cancelled executions.
    GDR_LOG_INFO = 3,
    // Planning decisions.
    GDR_LOG_DEBUG = 4,
};
#ifndef __cplusplus
typedef uint32_t gdr_log_level;
#endif // __cplusplus

// A context: thread count, log settings, ONNX Runtime and model locations (opaque).
typedef struct gdr_context gdr_context;

// A reconstruction filter: one method, its parameters, image views and plan (opaque).
typedef struct gdr_filter gdr_filter;

// A frame bundle as read from an OpenEXR file, values as stored (opaque, immutable).
typedef struct gdr_frame gdr_frame;

// Log callback: a level (`gdr_log_level`) and a NUL-terminated message valid during the call.
typedef void (*gdr_log_fn)(void *user, uint32_t level, const char *message);

// Progress callback: `fraction` done in [0, 1]; return false to cancel.
typedef bool (*gdr_progress_fn)(void *user, double fraction);

// One parameter of a method, as `gdr_method_param` describes it; its strings are static.
//
// The one struct that crosses the ABI, versioned by its first field: set `size` to
// `sizeof(gdr_param_info)` before the call. Later versions only append fields and fill no more
// than `size` bytes, so a program built against this header keeps working.
typedef struct {
    // Set by the caller: `sizeof(gdr_param_info)`.
    size_t size;
    // The name the setters take.
    const char *name;
    // Its kind: which setter it takes.
    gdr_param_kind kind;
    // Lowest accepted value (a choice: 0; a bool: 0).
    double min;
    // Highest accepted value (a choice: the last index; a bool: 1).
    double max;
    // `min` itself is not accepted.
    bool min_exclusive;
    // `max` itself is not accepted.
    bool max_exclusive;
    // The default (a bool as 0 or 1, a choice as its index).
    double default_value;
    // A choice's names by index, separated by commas (`"rdfc,l1,none"`); `""` otherwise.
    const char *choices;
    // One line: what it does.
    const char *doc;
} gdr_param_info;

#ifdef __cplusplus
extern "C" {
#endif // __cplusplus

// Return the library's version as `MAJOR * 10000 + MINOR * 100 + PATCH` (compare with `GDR_VERSION`).
uint32_t gdr_version(void);

// Return and clear the status of the last failed call on this thread (`GDR_ERROR_NONE` if none).
//
// If `message` is not NULL it receives a NUL-terminated description naming the function, the
// object (layer, parameter) and the problem, or "" when there is no error. The string is owned
// by the library and stays valid until the next `gdr_get_error` call on the same thread.
gdr_error gdr_get_error(const char **message);

// Return the name of a status code (`"GDR_ERROR_CANCELLED"`), a static string; unknown codes give `"GDR_ERROR_?"`.
const char *gdr_error_name(uint32_t code);

// Return the name of method `index` (`"l2"`, `"l1"`, ...) for `gdr_filter_new`, or NULL past the last one.
const char *gdr_method_name(uint32_t index);

// Create a context with default settings (all cores, log level WARNING) into `*out`; NULL on failure.
gdr_error gdr_context_new(gdr_context **out);

// Add a reference to `ctx`; each reference is dropped by one `gdr_context_release`.
gdr_error gdr_context_retain(gdr_context *ctx);

// Drop the reference `*ctx` and set `*ctx` to NULL (no-op when `*ctx` is NULL); the last one frees the context.
//
// Filters keep their context alive: releasing a context that filters still use is fine.
gdr_error gdr_context_release(gdr_context **ctx);

// Set an integer parameter: `"threads"` (0 = all cores; before commit), `"max_memory_mb"` (before commit) or `"log_level"` (a `gdr_log_level`, any time).
//
// `"max_memory_mb"`: the most memory, in MiB, one filter's plan may need beyond its images.
// As OIDN's `maxMemoryMB`, it sizes tiles: GradNet and the combiner (down to tiles of four
// margins a side) and OIDN's scratch (down to 512 MiB) run in smaller tiles to fit, the same
// image up to rounding in more time; `"auto"` leaves out the paths that do not fit.
// `gdr_filter_commit` refuses a method and size whose estimate (buffers, scratch, output,
// OIDN's or ONNX Runtime's share) is over it even so with `GDR_ERROR_OUT_OF_MEMORY` and a
// message giving the estimate and the limit. 0 (the default) is no limit. On Linux the address space left under
// the process's limit (`ulimit -v`) bounds a commit the same way.
gdr_error gdr_context_set_int(gdr_context *ctx, const char *name, int32_t value);

// Read an integer parameter into `*value`: `"threads"` (the pool's thread count once committed, else the setting), `"max_memory_mb"` or `"log_level"`.
gdr_error gdr_context_get_int(const gdr_context *ctx, const char *name, int32_t *value);

// Set a string parameter before commit: `"onnxruntime_path"` (ONNX Runtime library), `"model_path"` (GradNet model) or `"oidn_path"` (Open Image Denoise library, for the prior); NULL clears it.
//
// Paths are stored as given and only opened when a method needs them.
gdr_error gdr_context_set_string(gdr_context *ctx, const char *name, const char *value);

// Set (or with NULL remove) the log callback; it may be called from any thread, never concurrently for one context.
//
// Calls for one context are serialised (a lock is held while the callback runs). Replacing or
// removing the callback waits for a running call to return: afterwards the old callback is
// never called again. The callback may call any gdr_ function except this one on the same
// context (`GDR_ERROR_INVALID_OPERATION`); what those calls would log on the same context is
// dropped, not delivered. It must not wait for a thread that is replacing the callback.
gdr_error gdr_context_set_log_callback(gdr_context *ctx, gdr_log_fn callback, void *user);

// Apply the settings and start the thread pool; filters can be created afterwards.
//
// Committing twice is an error (`GDR_ERROR_INVALID_OPERATION`); so is setting `threads` or a path afterwards.
gdr_error gdr_context_commit(gdr_context *ctx);

// Create a filter running `method` (`"l2"`, `"l1"`, `"frgr"`, `"gradnet"`, `"prior"`, `"combiner"`, `"auto"`; see `gdr_method_name`) on a committed context into `*out`; NULL on failure.
gdr_error gdr_filter_new(gdr_context *ctx, const char *method, gdr_filter **out);

// Add a reference to `filter`; each reference is dropped by one `gdr_filter_release`.
gdr_error gdr_filter_retain(gdr_filter *filter);

// Drop the reference `*filter` and set `*filter` to NULL (no-op when `*filter` is NULL); the last one frees the filter.
//
// After a cancelled execute of a prior path, the last release waits for Open Image Denoise's
// operation in flight to end (at most 0.35 s at 1280 x 720 on two cores; see
// `gdr_filter_cancel`).
gdr_error gdr_filter_release(gdr_filter **filter);

// Reset every parameter of the filter's method to one of its presets (`"prior"`, `"fast"`, `"published"` for `"l1"`; `"fast"`, `"reference"` for `"frgr"`; docs/PARAMETERS.md and `gdrecon params` list them); `"spp"` and `"strict"` are kept.
//
// An unknown preset is `GDR_ERROR_INVALID_ARGUMENT`, with a message that lists the method's presets.
gdr_error gdr_filter_set_preset(gdr_filter *filter, const char *name);

// Set a float parameter of the filter's method (see `gdr_method_param`, or docs/PARAMETERS.md), or `"spp"` (0 = unknown).
//
// An unknown name, a parameter of another type or a value out of its range is
// `GDR_ERROR_INVALID_ARGUMENT`, with a message that lists the names or states the range.
gdr_error gdr_filter_set_float(gdr_filter *filter, const char *name, float value);

// Set an integer parameter of the filter's method, or a choice by its index (filter `"guide"`: a `GDR_FRGR_GUIDE_*` value; l2 and l1 `"data"`: a `GDR_DATA_*` value).
gdr_error gdr_filter_set_int(gdr_filter *filter, const char *name, int32_t value);

// Set a boolean parameter of the filter's method, or `"strict"` (NaN/Inf/negative input is an error instead of replaced).
gdr_error gdr_filter_set_bool(gdr_filter *filter, const char *name, bool value);

// Read a float parameter into `*value`.
gdr_error gdr_filter_get_float(gdr_filter *filter, const char *name, float *value);

// Read an integer (or choice index) parameter into `*value`.
gdr_error gdr_filter_get_int(gdr_filter *filter, const char *name, int32_t *value);

// Read a boolean parameter into `*value`.
gdr_error gdr_filter_get_bool(gdr_filter *filter, const char *name, bool *value);

// Set image `name` to an interleaved view: pixel (x, y) channel c at `ptr + y*row_stride + x*pixel_stride + 4*c` bytes.
//
// Names: `"color"`, `"dx"`, `"dy"` (required), `"variance"`, `"albedo"`, `"normal"` (3 channels),
// `"depth"` (1 channel) and `"output"` (required, 3 channels, written by `gdr_filter_execute`,
// so its memory must be writable). Strides are in bytes; 0 means packed (`pixel_stride =
// 4 * channels`, `row_stride = width * pixel_stride`). For RGBA buffers pass 3 channels and a
// pixel stride of 16. The memory is borrowed, not copied: it must stay valid until the next
// execute returns.
gdr_error gdr_filter_set_image(gdr_filter *filter, const char *name, const float *ptr, size_t width, size_t height, size_t channels, size_t pixel_stride, size_t row_stride);

// Set image `name` to a planar view: pixel (x, y) channel c at `ptr + c*plane_stride + y*row_stride + 4*x` bytes.
//
// Same names and rules as `gdr_filter_set_image`; 0 strides mean packed (`row_stride = 4 *
// width`, `plane_stride = height * row_stride`).
gdr_error gdr_filter_set_image_planar(gdr_filter *filter, const char *name, const float *ptr, size_t width, size_t height, size_t channels, size_t row_stride, size_t plane_stride);

// Remove image `name` (an optional layer the method should not use); removing an unset image is not an error.
gdr_error gdr_filter_unset_image(gdr_filter *filter, const char *name);

// Set (or with NULL remove) the progress callback; it runs on a library thread during execute, never concurrently with itself.
//
// It receives the fraction done in [0, 1] and returns false to cancel. It must not throw.
// Calls on the same filter from it fail with `GDR_ERROR_INVALID_OPERATION`, except
// `gdr_filter_cancel`, `gdr_filter_retain` and `gdr_filter_release` (releasing the last
// reference is safe: execute holds its own until it returns).
gdr_error gdr_filter_set_progress_callback(gdr_filter *filter, gdr_progress_fn callback, void *user);

// Validate the images and parameters and plan the method for the image size (expensive the first time; cheap when only pointers changed).
//
// Errors: a required image missing, or method `"frgr"` without `"spp"` (its weights depend on
// the sample count) (`GDR_ERROR_INVALID_OPERATION`), sizes that disagree
// (`GDR_ERROR_INVALID_IMAGE`), an output partially overlapping an input (`GDR_ERROR_OVERLAP`;
// the output may be exactly an input view, i.e. in place), a parameter out of range
// (`GDR_ERROR_INVALID_ARGUMENT`), a plan over the context's `"max_memory_mb"`
// (`GDR_ERROR_OUT_OF_MEMORY`). With image `"prior"` set, the plan does not count Open Image
// Denoise's scratch memory, which it then never needs.
gdr_error gdr_filter_commit(gdr_filter *filter);

// Run the committed filter: read the input views, reconstruct, write the output view; blocks until done.
//
// Errors: not committed since the last change (`GDR_ERROR_INVALID_OPERATION`), bad values in
// strict mode (`GDR_ERROR_INVALID_INPUT`), cancelled (`GDR_ERROR_CANCELLED`; the output is then
// left untouched).
gdr_error gdr_filter_execute(gdr_filter *filter);

// Ask a running execute on `filter` to stop (it returns `GDR_ERROR_CANCELLED` promptly); callable from any thread, lock-free.
//
// A cancel when no execute is running has no effect (each execute starts uncancelled).
// Every method returns within about 60 ms of the cancel at 1280 x 720. Open Image Denoise
// (the prior paths) stops only between its operations, up to 0.35 s apart: the execute
// returns at once, OIDN finishes its operation in the background on buffers the filter owns
// (none of the caller's); the filter's next execute waits for it (cancellably), and so does
// its last release, so that nothing of a released filter goes on running.
gdr_error gdr_filter_cancel(gdr_filter *filter);

// Point `*text` at the report of the last successful execute ("" before the first); valid until the next execute or release.
gdr_error gdr_filter_get_report(gdr_filter *filter, const char **text);

// Read the frame bundle (multi-layer OpenEXR) at `path` into `*out`; NULL on failure (`GDR_ERROR_IO`).
//
// Values are not validated here: the filter that uses the layers applies its policy.
gdr_error gdr_frame_read(const char *path, gdr_frame **out);

// Free `*frame` and set `*frame` to NULL (no-op when `*frame` is NULL); layer pointers die with it.
gdr_error gdr_frame_release(gdr_frame **frame);

// Write the frame's width, height and samples per pixel (0 when unknown) into the non-NULL arguments.
gdr_error gdr_frame_get_info(const gdr_frame *frame, size_t *width, size_t *height, float *spp);

// Point `*data` at layer `name` as packed planar floats (`channels` planes of width x height) and set `*channels`; NULL and 0 when absent.
//
// Names: `color`, `dx`, `dy`, `variance`, `albedo`, `normal`, `depth`, `reference`. Pass the
// layer to `gdr_filter_set_image_planar` with 0 strides. Valid until the frame is released.
gdr_error gdr_frame_get_layer(const gdr_frame *frame, const char *name, const float **data, size_t *channels);

// Write into `*count` how many parameters a filter running `method` takes (the method's own, then `"spp"` and `"strict"`).
gdr_error gdr_method_param_count(const char *method, size_t *count);

// Describe parameter `index` (0 to count - 1) of `method` in `*info` (whose `size` the caller sets to `sizeof(gdr_param_info)`): name, kind, range, default, choices, documentation; its strings are static.
gdr_error gdr_method_param(const char *method, size_t index, gdr_param_info *info);

#ifdef __cplusplus
}  // extern "C"
#endif  // __cplusplus

#endif  /* GDRECON_H */
