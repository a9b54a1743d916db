// Tests of include/gdrecon.hpp, the C++17 wrapper (tests/c/run.sh compiles it with -Wall
// -Wextra -Werror -pedantic and runs it, also under valgrind):
//   test_cpp [SAMPLE.exr]
// Results equal the C API's bit for bit; failures throw gdr::Error with their code; a cancel
// is execute() == false; handles move; parameters are listed with ranges, defaults and
// choices. The last line is "N passed, N failed".
#include <cmath>
#include <cstdio>
#include <cstring>
#include <string>
#include <type_traits>
#include <vector>

#include "gdrecon.hpp"

static_assert(!std::is_copy_constructible_v<gdr::Context>, "contexts are move-only");
static_assert(!std::is_copy_constructible_v<gdr::Filter>, "filters are move-only");
static_assert(std::is_nothrow_move_constructible_v<gdr::Filter>, "filters move without throwing");

namespace {

int passed = 0, failed = 0;

void check(bool ok, const char* what, int line) {
    if (ok) {
        ++passed;
    } else {
        ++failed;
        std::fprintf(stderr, "FAIL line %d: %s\n", line, what);
    }
}
#define CHECK(cond) check((cond), #cond, __LINE__)

// Runs `body`, which must throw gdr::Error with `code`; returns its message.
template <class Body>
std::string throws(Body body, gdr_error code, int line) {
    try {
        body();
    } catch (const gdr::Error& e) {
        check(e.code() == code, "the expected code", line);
        if (e.code() != code) std::fprintf(stderr, "  got %s\n", e.what());
        return e.what();
    }
    check(false, "an exception", line);
    return "";
}
#define THROWS(body, code) throws([&] { body; }, (code), __LINE__)

constexpr size_t W = 40, H = 24;

struct Frame {
    std::vector<float> color, dx, dy;
    Frame() : color(W * H * 3), dx(W * H * 3), dy(W * H * 3) {
        for (size_t y = 0; y < H; ++y)
            for (size_t x = 0; x < W; ++x)
                for (size_t c = 0; c < 3; ++c) {
                    size_t p = (y * W + x) * 3 + c;
                    color[p] = 0.3f + 0.02f * static_cast<float>((x * 5 + y * 3 + c * 7) % 11);
                    dx[p] = x + 1 < W ? 0.01f * static_cast<float>(c) : 0.0f;
                    dy[p] = y + 1 < H ? -0.005f : 0.0f;
                }
    }
};

// The same reconstruction through the C API.
std::vector<float> with_c(const Frame& fr, const char* method) {
    std::vector<float> out(W * H * 3);
    gdr_context* ctx = nullptr;
    gdr_filter* f = nullptr;
    bool ok = gdr_context_new(&ctx) == GDR_ERROR_NONE &&
              gdr_context_set_int(ctx, "threads", 2) == GDR_ERROR_NONE &&
              gdr_context_commit(ctx) == GDR_ERROR_NONE &&
              gdr_filter_new(ctx, method, &f) == GDR_ERROR_NONE &&
              gdr_filter_set_image(f, "color", fr.color.data(), W, H, 3, 0, 0) == GDR_ERROR_NONE &&
              gdr_filter_set_image(f, "dx", fr.dx.data(), W, H, 3, 0, 0) == GDR_ERROR_NONE &&
              gdr_filter_set_image(f, "dy", fr.dy.data(), W, H, 3, 0, 0) == GDR_ERROR_NONE &&
              gdr_filter_set_image(f, "output", out.data(), W, H, 3, 0, 0) == GDR_ERROR_NONE &&
              gdr_filter_commit(f) == GDR_ERROR_NONE && gdr_filter_execute(f) == GDR_ERROR_NONE;
    CHECK(ok);
    gdr_filter_release(&f);
    gdr_context_release(&ctx);
    return out;
}

gdr::Context context(int threads = 2) {
    gdr::Context ctx;
    ctx.set("threads", threads);
    ctx.commit();
    return ctx;
}

void set_inputs(gdr::Filter& f, const Frame& fr) {
    f.setImage("color", fr.color.data(), W, H);
    f.setImage("dx", fr.dx.data(), W, H);
    f.setImage("dy", fr.dy.data(), W, H);
}

void test_results_equal_the_c_api() {
    Frame fr;
    gdr::Context ctx = context();
    CHECK(ctx.getInt("threads") == 2);
    for (const char* method : {"l2", "l1"}) {
        std::vector<float> out(W * H * 3);
        gdr::Filter f(ctx, method);
        set_inputs(f, fr);
        f.setImage("output", out.data(), W, H);
        f.commit();
        CHECK(f.execute());
        CHECK(f.report().find(std::string("method ") + method) != std::string::npos);
        std::vector<float> expected = with_c(fr, method);
        CHECK(std::memcmp(out.data(), expected.data(), out.size() * sizeof(float)) == 0);
    }
    // RGBA in place, through the pixel stride: the RGB of the result equals packed output.
    std::vector<float> rgba(W * H * 4, 1.0f);
    for (size_t p = 0; p < W * H; ++p)
        for (size_t c = 0; c < 3; ++c) rgba[p * 4 + c] = fr.color[p * 3 + c];
    gdr::Filter f(ctx, "l2");
    set_inputs(f, fr);
    f.setImage("color", rgba.data(), W, H, 3, 16);
    f.setImage("output", rgba.data(), W, H, 3, 16);
    f.commit();
    CHECK(f.execute());
    std::vector<float> expected = with_c(fr, "l2");
    bool same = true;
    for (size_t p = 0; p < W * H; ++p) {
        for (size_t c = 0; c < 3; ++c) same = same && rgba[p * 4 + c] == expected[p * 3 + c];
        same = same && rgba[p * 4 + 3] == 1.0f;
    }
    CHECK(same);
}

void test_errors_throw() {
    Frame fr;
    std::vector<float> out(W * H * 3);
    gdr::Context raw;
    THROWS(gdr::Filter(raw, "l2"), GDR_ERROR_INVALID_OPERATION);  // not committed
    THROWS(raw.set("threads", -1), GDR_ERROR_INVALID_ARGUMENT);
    THROWS(raw.set("nope", std::string("x")), GDR_ERROR_INVALID_ARGUMENT);
    gdr::Context ctx = context();
    std::string m = THROWS(gdr::Filter(ctx, "gradnot"), GDR_ERROR_INVALID_ARGUMENT);
    CHECK(m.find("GDR_ERROR_INVALID_ARGUMENT") == 0 && m.find("l2") != std::string::npos);
    gdr::Filter f(ctx, "l1");
    m = THROWS(f.set("alpha", -1.0f), GDR_ERROR_INVALID_ARGUMENT);
    CHECK(m.find("(0, 10000]") != std::string::npos);
    THROWS(f.set("alpha", true), GDR_ERROR_INVALID_ARGUMENT);  // wrong type
    THROWS(f.getInt("alpha"), GDR_ERROR_INVALID_ARGUMENT);
    f.set("alpha", 0.3);  // a double literal is a float parameter
    CHECK(f.getFloat("alpha") == 0.3f);
    f.set("reweight_steps", 3);
    CHECK(f.getInt("reweight_steps") == 3);
    f.set("strict", true);
    CHECK(f.getBool("strict"));
    THROWS(f.execute(), GDR_ERROR_INVALID_OPERATION);  // never committed
    THROWS(f.commit(), GDR_ERROR_INVALID_OPERATION);   // images missing
    THROWS(f.setImage("color", fr.color.data(), W, H, 4), GDR_ERROR_INVALID_IMAGE);
    THROWS(f.setImage("colour", fr.color.data(), W, H), GDR_ERROR_INVALID_ARGUMENT);
    set_inputs(f, fr);
    f.setImage("output", fr.dx.data() + 3, W, H - 1);
    f.setImage("dx", fr.dx.data(), W, H - 1);
    f.setImage("color", fr.color.data(), W, H - 1);
    f.setImage("dy", fr.dy.data(), W, H - 1);
    THROWS(f.commit(), GDR_ERROR_OVERLAP);
    f.unsetImage("output");
    THROWS(f.setPreset("nope"), GDR_ERROR_INVALID_ARGUMENT);
    f.setPreset("fast");
    THROWS(gdr::params("gradnot"), GDR_ERROR_INVALID_ARGUMENT);
    gdr_error none = gdr_get_error(nullptr);
    CHECK(none == GDR_ERROR_NONE);  // every failure's message was consumed by its exception
}

void test_cancel_and_callbacks() {
    Frame fr;
    std::vector<float> out(W * H * 3, -1.0f);
    gdr::Context ctx;
    ctx.set("threads", 2);
    std::vector<std::string> lines;
    int infos = 0;
    ctx.setLogCallback([&](gdr::LogLevel level, const char* message) {
        lines.emplace_back(message);
        if (level == gdr::LogLevel::Info) ++infos;
    });
    ctx.set("log_level", gdr::LogLevel::Info);
    ctx.commit();
    gdr::Filter f(ctx, "l1");
    set_inputs(f, fr);
    f.setImage("output", out.data(), W, H);
    f.commit();
    int calls = 0;
    f.setProgressMonitor([&](double) { return ++calls < 2; });
    CHECK(!f.execute());  // cancelled: not an exception
    CHECK(calls == 2);
    CHECK(out[0] == -1.0f);  // untouched
    CHECK(infos == 1);       // the cancel, at Info
    f.setProgressMonitor([&](double) -> bool { throw std::runtime_error("from the callback"); });
    CHECK(!f.execute());  // an exception out of the callback cancels
    f.setProgressMonitor(nullptr);
    CHECK(f.execute());
    CHECK(infos == 3);  // a second cancel, the report
    ctx.setLogCallback(nullptr);
    CHECK(f.execute());
    CHECK(lines.size() == 3);
}

void test_moves() {
    gdr::Context a = context(1);
    gdr::Context b(std::move(a));
    CHECK(!a && b);
    gdr::Filter f(b, "l2");
    gdr::Filter g(std::move(f));
    CHECK(!f && g);
    f = std::move(g);
    CHECK(f && !g);
    a = std::move(b);
    CHECK(a && !b);
    // A filter keeps its context alive, and outlives the Context object.
    gdr::Filter h(a, "l2");
    a = gdr::Context();
    Frame fr;
    std::vector<float> out(W * H * 3);
    set_inputs(h, fr);
    h.setImage("output", out.data(), W, H);
    h.commit();
    CHECK(h.execute());
}

void test_params() {
    std::vector<std::string> methods = gdr::methods();
    CHECK(methods.size() >= 5 && methods[0] == "l2" && methods[1] == "l1");
    gdr::Context ctx = context(1);
    bool saw_choice = false, saw_exclusive = false;
    for (const std::string& method : methods) {
        std::vector<gdr::ParamInfo> all = gdr::params(method);
        CHECK(all.size() >= 2 && all[all.size() - 2].name == "spp" && all.back().name == "strict");
        gdr::Filter f(ctx, method);
        for (const gdr::ParamInfo& p : all) {
            CHECK(!p.doc.empty() && p.min <= p.max && p.accepts(p.defaultValue));
            // The default round-trips through the setter of its kind.
            switch (p.kind) {
            case GDR_PARAM_FLOAT:
                f.set(p.name.c_str(), static_cast<float>(p.defaultValue));
                CHECK(f.getFloat(p.name.c_str()) == static_cast<float>(p.defaultValue));
                break;
            case GDR_PARAM_INT:
            case GDR_PARAM_CHOICE:
                f.set(p.name.c_str(), static_cast<int>(p.defaultValue));
                CHECK(f.getInt(p.name.c_str()) == static_cast<int>(p.defaultValue));
                break;
            case GDR_PARAM_BOOL:
                f.set(p.name.c_str(), p.defaultValue != 0);
                CHECK(f.getBool(p.name.c_str()) == (p.defaultValue != 0));
                break;
            }
            if (p.kind == GDR_PARAM_CHOICE) {
                saw_choice = true;
                CHECK(!p.choices.empty() && p.max == static_cast<double>(p.choices.size() - 1));
                THROWS(f.set(p.name.c_str(), static_cast<int>(p.choices.size())),
                       GDR_ERROR_INVALID_ARGUMENT);
            } else {
                CHECK(p.choices.empty());
            }
            if (p.minExclusive && p.kind == GDR_PARAM_FLOAT) {
                saw_exclusive = true;
                CHECK(!p.accepts(p.min));
                THROWS(f.set(p.name.c_str(), static_cast<float>(p.min)), GDR_ERROR_INVALID_ARGUMENT);
            }
        }
    }
    CHECK(saw_choice && saw_exclusive);
}

void test_frame(const char* sample) {
    THROWS(gdr::Frame("/nonexistent/frame.exr"), GDR_ERROR_IO);
    gdr::Frame frame(sample);
    CHECK(frame.width() > 0 && frame.height() > 0 && frame.spp() > 0);
    gdr::Frame moved(std::move(frame));
    CHECK(moved.get() && !frame.get());
    gdr::Frame::Layer color = moved.layer("color");
    CHECK(color && color.channels == 3);
    CHECK(moved.layer("depth").channels == 1);
    THROWS(moved.layer("colour"), GDR_ERROR_INVALID_ARGUMENT);
    gdr::Context ctx = context();
    gdr::Filter f(ctx, "l2");
    std::vector<float> out(moved.width() * moved.height() * 3);
    for (const char* name : {"color", "dx", "dy"}) {
        gdr::Frame::Layer l = moved.layer(name);
        f.setImagePlanar(name, l.data, moved.width(), moved.height(), l.channels);
    }
    f.setImage("output", out.data(), moved.width(), moved.height());
    f.commit();
    CHECK(f.execute());
}

}  // namespace

int main(int argc, char** argv) {
    CHECK(gdr::version() == GDR_VERSION);
    try {
        test_results_equal_the_c_api();
        test_errors_throw();
        test_cancel_and_callbacks();
        test_moves();
        test_params();
        if (argc > 1) test_frame(argv[1]);
    } catch (const std::exception& e) {
        std::fprintf(stderr, "FAIL: unexpected exception: %s\n", e.what());
        ++failed;
    }
    std::printf("%d passed, %d failed\n", passed, failed);
    return failed ? 1 : 0;
}
