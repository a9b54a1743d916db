// gdrecon: C++17 wrapper of the C API (include/gdrecon.h), header-only.
//
// Move-only RAII handles in the style of Open Image Denoise's oidn.hpp: gdr::Context and
// gdr::Filter release their handle when destroyed; every failure throws gdr::Error, which
// carries the status code and the library's message. A cancelled execute is not a failure:
// Filter::execute returns false. The C header's rules (threads, callbacks, fork) apply
// unchanged.
//
//   gdr::Context ctx;                     // gdr_context_new
//   ctx.set("threads", 4);
//   ctx.commit();
//   gdr::Filter f(ctx, "l1");
//   f.set("alpha", 0.2f);
//   f.setImage("color", rgba, w, h, 3, 16);      // RGB read out of RGBA
//   f.setImage("dx", dx, w, h);                  // packed RGB
//   f.setImage("dy", dy, w, h);
//   f.setImage("output", rgba, w, h, 3, 16);     // in place
//   f.commit();
//   f.execute();
//
// gdr::params("l1") lists a method's parameters (gdr_method_param): kind, range, default,
// choices, documentation.
#ifndef GDRECON_HPP
#define GDRECON_HPP

#include <cstddef>
#include <cstdint>
#include <exception>
#include <functional>
#include <memory>
#include <stdexcept>
#include <string>
#include <utility>
#include <vector>

#include "gdrecon.h"

namespace gdr {

// A failed call: the status code and the message from gdr_get_error.
class Error : public std::runtime_error {
public:
    Error(gdr_error code, const std::string& message)
        : std::runtime_error(std::string(gdr_error_name(code)) + ": " + message), code_(code) {}
    gdr_error code() const noexcept { return code_; }

private:
    gdr_error code_;
};

// Throws the calling thread's last error when `code` is not GDR_ERROR_NONE.
inline void check(gdr_error code) {
    if (code == GDR_ERROR_NONE) return;
    const char* message = "";
    gdr_get_error(&message);
    throw Error(code, message ? message : "");
}

// The library's version (MAJOR * 10000 + MINOR * 100 + PATCH); compare with GDR_VERSION.
inline uint32_t version() noexcept { return gdr_version(); }

// The methods a Filter can run ("l2", "l1", ...).
inline std::vector<std::string> methods() {
    std::vector<std::string> names;
    for (uint32_t i = 0; const char* name = gdr_method_name(i); ++i) names.emplace_back(name);
    return names;
}

// One parameter of a method, as gdr_method_param describes it.
struct ParamInfo {
    std::string name;
    gdr_param_kind kind = GDR_PARAM_FLOAT;
    double min = 0, max = 0;
    bool minExclusive = false, maxExclusive = false;
    double defaultValue = 0;              // a bool as 0 or 1, a choice as its index
    std::vector<std::string> choices;     // a choice's names by index
    std::string doc;

    // True when `value` lies in the accepted range.
    bool accepts(double value) const {
        bool above = minExclusive ? value > min : value >= min;
        bool below = maxExclusive ? value < max : value <= max;
        return above && below;
    }
};

// The parameters a Filter running `method` takes (the method's, then "spp" and "strict").
inline std::vector<ParamInfo> params(const std::string& method) {
    size_t count = 0;
    check(gdr_method_param_count(method.c_str(), &count));
    std::vector<ParamInfo> all;
    all.reserve(count);
    for (size_t i = 0; i < count; ++i) {
        gdr_param_info c{};
        c.size = sizeof c;
        check(gdr_method_param(method.c_str(), i, &c));
        ParamInfo p;
        p.name = c.name;
        p.kind = c.kind;
        p.min = c.min;
        p.max = c.max;
        p.minExclusive = c.min_exclusive;
        p.maxExclusive = c.max_exclusive;
        p.defaultValue = c.default_value;
        p.doc = c.doc;
        for (std::string rest = c.choices; !rest.empty();) {
            size_t comma = rest.find(',');
            p.choices.push_back(rest.substr(0, comma));
            rest = comma == std::string::npos ? std::string() : rest.substr(comma + 1);
        }
        all.push_back(std::move(p));
    }
    return all;
}

// Log levels (gdr_log_level).
enum class LogLevel : uint32_t {
    None = GDR_LOG_NONE,
    Error = GDR_LOG_ERROR,
    Warning = GDR_LOG_WARNING,
    Info = GDR_LOG_INFO,
    Debug = GDR_LOG_DEBUG,
};

// A context: threads and global settings. Set, commit, then create filters.
class Context {
public:
    using LogFunction = std::function<void(LogLevel, const char*)>;

    Context() { check(gdr_context_new(&handle_)); }
    // Takes over one reference to an existing handle.
    explicit Context(gdr_context* handle) noexcept : handle_(handle) {}
    Context(Context&& other) noexcept
        : handle_(std::exchange(other.handle_, nullptr)), log_(std::move(other.log_)) {}
    Context& operator=(Context&& other) noexcept {
        if (this != &other) {
            reset();
            handle_ = std::exchange(other.handle_, nullptr);
            log_ = std::move(other.log_);
        }
        return *this;
    }
    Context(const Context&) = delete;
    Context& operator=(const Context&) = delete;
    ~Context() { reset(); }

    // "threads" (before commit) or "log_level".
    void set(const char* name, int value) { check(gdr_context_set_int(handle_, name, value)); }
    void set(const char* name, LogLevel level) { set(name, static_cast<int>(level)); }
    // "onnxruntime_path", "model_path", "oidn_path" (before commit).
    void set(const char* name, const std::string& value) {
        check(gdr_context_set_string(handle_, name, value.c_str()));
    }
    void set(const char* name, const char* value) {
        check(gdr_context_set_string(handle_, name, value));
    }
    int getInt(const char* name) const {
        int32_t value = 0;
        check(gdr_context_get_int(handle_, name, &value));
        return value;
    }

    // Sets (or with an empty function removes) the log callback. It must not throw: an
    // exception it lets out is swallowed. Calls never overlap (see gdrecon.h). It is removed
    // when this object is destroyed, even if filters still keep the context alive.
    void setLogCallback(LogFunction f) {
        if (!f) {
            check(gdr_context_set_log_callback(handle_, nullptr, nullptr));
            log_.reset();
            return;
        }
        auto next = std::make_unique<LogFunction>(std::move(f));
        check(gdr_context_set_log_callback(handle_, &Context::onLog, next.get()));
        log_ = std::move(next);  // the old one is no longer called once the C call returns
    }

    void commit() { check(gdr_context_commit(handle_)); }

    gdr_context* get() const noexcept { return handle_; }
    explicit operator bool() const noexcept { return handle_ != nullptr; }

private:
    static void onLog(void* user, uint32_t level, const char* message) {
        try {
            (*static_cast<LogFunction*>(user))(static_cast<LogLevel>(level), message);
        } catch (...) {
        }
    }
    void reset() noexcept {
        // Filters keep the context alive: remove the callback (waiting for a running call)
        // before `log_` goes.
        if (handle_ && log_ && gdr_context_set_log_callback(handle_, nullptr, nullptr) != GDR_ERROR_NONE)
            gdr_get_error(nullptr);
        gdr_context_release(&handle_);
        log_.reset();
    }

    gdr_context* handle_ = nullptr;
    std::unique_ptr<LogFunction> log_;
};

// A filter: one method, its parameters, image views and plan.
class Filter {
public:
    // Returns false to cancel.
    using ProgressFunction = std::function<bool(double)>;

    Filter(const Context& context, const std::string& method) {
        check(gdr_filter_new(context.get(), method.c_str(), &handle_));
    }
    explicit Filter(gdr_filter* handle) noexcept : handle_(handle) {}
    Filter(Filter&& other) noexcept
        : handle_(std::exchange(other.handle_, nullptr)), progress_(std::move(other.progress_)) {}
    Filter& operator=(Filter&& other) noexcept {
        if (this != &other) {
            reset();
            handle_ = std::exchange(other.handle_, nullptr);
            progress_ = std::move(other.progress_);
        }
        return *this;
    }
    Filter(const Filter&) = delete;
    Filter& operator=(const Filter&) = delete;
    ~Filter() { reset(); }

    void set(const char* name, float value) { check(gdr_filter_set_float(handle_, name, value)); }
    void set(const char* name, double value) { set(name, static_cast<float>(value)); }
    void set(const char* name, int value) { check(gdr_filter_set_int(handle_, name, value)); }
    void set(const char* name, bool value) { check(gdr_filter_set_bool(handle_, name, value)); }
    void setPreset(const char* name) { check(gdr_filter_set_preset(handle_, name)); }

    float getFloat(const char* name) const {
        float value = 0;
        check(gdr_filter_get_float(handle_, name, &value));
        return value;
    }
    int getInt(const char* name) const {
        int32_t value = 0;
        check(gdr_filter_get_int(handle_, name, &value));
        return value;
    }
    bool getBool(const char* name) const {
        bool value = false;
        check(gdr_filter_get_bool(handle_, name, &value));
        return value;
    }

    // An interleaved view (byte strides, 0 = packed); the memory is borrowed.
    void setImage(const char* name, const float* data, size_t width, size_t height,
                  size_t channels = 3, size_t pixelStride = 0, size_t rowStride = 0) {
        check(gdr_filter_set_image(handle_, name, data, width, height, channels, pixelStride,
                                   rowStride));
    }
    // A planar view (byte strides, 0 = packed).
    void setImagePlanar(const char* name, const float* data, size_t width, size_t height,
                        size_t channels = 3, size_t rowStride = 0, size_t planeStride = 0) {
        check(gdr_filter_set_image_planar(handle_, name, data, width, height, channels, rowStride,
                                          planeStride));
    }
    void unsetImage(const char* name) { check(gdr_filter_unset_image(handle_, name)); }

    // Sets (or with an empty function removes) the progress callback. An exception it lets
    // out cancels the execution. It lives as long as this object: do not let a reference
    // retained through get() execute after this object is destroyed.
    void setProgressMonitor(ProgressFunction f) {
        if (!f) {
            check(gdr_filter_set_progress_callback(handle_, nullptr, nullptr));
            progress_.reset();
            return;
        }
        auto next = std::make_unique<ProgressFunction>(std::move(f));
        check(gdr_filter_set_progress_callback(handle_, &Filter::onProgress, next.get()));
        progress_ = std::move(next);
    }

    void commit() { check(gdr_filter_commit(handle_)); }
    // Runs the filter; false when cancelled (the output is then untouched), else throws.
    bool execute() {
        gdr_error code = gdr_filter_execute(handle_);
        if (code == GDR_ERROR_CANCELLED) {
            gdr_get_error(nullptr);
            return false;
        }
        check(code);
        return true;
    }
    // Asks a running execute to stop; any thread, any time.
    void cancel() noexcept { gdr_filter_cancel(handle_); }
    // The last successful execute's report.
    std::string report() const {
        const char* text = "";
        check(gdr_filter_get_report(handle_, &text));
        return text;
    }

    gdr_filter* get() const noexcept { return handle_; }
    explicit operator bool() const noexcept { return handle_ != nullptr; }

private:
    static bool onProgress(void* user, double fraction) {
        try {
            return (*static_cast<ProgressFunction*>(user))(fraction);
        } catch (...) {
            return false;
        }
    }
    void reset() noexcept {
        gdr_filter_release(&handle_);
        progress_.reset();
    }

    gdr_filter* handle_ = nullptr;
    std::unique_ptr<ProgressFunction> progress_;
};

// A frame bundle read from an OpenEXR file (gdr_frame), for callers without an EXR reader.
class Frame {
public:
    // One layer: packed planar floats (`channels` planes of width x height), or null.
    struct Layer {
        const float* data = nullptr;
        size_t channels = 0;
        explicit operator bool() const noexcept { return data != nullptr; }
    };

    explicit Frame(const std::string& path) {
        check(gdr_frame_read(path.c_str(), &handle_));
        check(gdr_frame_get_info(handle_, &width_, &height_, &spp_));
    }
    Frame(Frame&& other) noexcept
        : handle_(std::exchange(other.handle_, nullptr)), width_(other.width_),
          height_(other.height_), spp_(other.spp_) {}
    Frame& operator=(Frame&& other) noexcept {
        if (this != &other) {
            gdr_frame_release(&handle_);
            handle_ = std::exchange(other.handle_, nullptr);
            width_ = other.width_;
            height_ = other.height_;
            spp_ = other.spp_;
        }
        return *this;
    }
    Frame(const Frame&) = delete;
    Frame& operator=(const Frame&) = delete;
    ~Frame() { gdr_frame_release(&handle_); }

    size_t width() const noexcept { return width_; }
    size_t height() const noexcept { return height_; }
    // Samples per pixel, 0 when unknown.
    float spp() const noexcept { return spp_; }
    // Layer `name` ("color", "dx", ...); empty when the bundle lacks it. Valid while this
    // object lives: pass it to Filter::setImagePlanar.
    Layer layer(const char* name) const {
        Layer l;
        check(gdr_frame_get_layer(handle_, name, &l.data, &l.channels));
        return l;
    }

    gdr_frame* get() const noexcept { return handle_; }

private:
    gdr_frame* handle_ = nullptr;
    size_t width_ = 0, height_ = 0;
    float spp_ = 0;
};

}  // namespace gdr

#endif  // GDRECON_HPP
