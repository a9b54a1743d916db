// The same as reconstruct.c in C++, with the buffers a renderer would have: one interleaved
// RGBA float buffer per pass (copied here from the bundle), the result written in place into
// the colour buffer's RGB, alpha untouched. RAII wrappers release the handles; errors become
// exceptions.
//
//   reconstruct_cpp FRAME.exr OUT_PREFIX      -> OUT_PREFIX_l2.pfm, OUT_PREFIX_l1.pfm, ...
#include <cstdio>
#include <memory>
#include <stdexcept>
#include <string>
#include <vector>

#include "gdrecon.h"

namespace {

void check(gdr_error code, const char* what) {
    if (code == GDR_ERROR_NONE) return;
    const char* message = "";
    gdr_get_error(&message);
    throw std::runtime_error(std::string(what) + ": " + gdr_error_name(code) + ": " + message);
}
#define CHECKED(call) check((call), #call)

struct ContextDeleter {
    void operator()(gdr_context* c) const { gdr_context_release(&c); }
};
struct FilterDeleter {
    void operator()(gdr_filter* f) const { gdr_filter_release(&f); }
};
struct FrameDeleter {
    void operator()(gdr_frame* f) const { gdr_frame_release(&f); }
};
using Context = std::unique_ptr<gdr_context, ContextDeleter>;
using Filter = std::unique_ptr<gdr_filter, FilterDeleter>;
using Frame = std::unique_ptr<gdr_frame, FrameDeleter>;

// A render pass as an interleaved RGBA buffer.
struct Rgba {
    size_t width = 0, height = 0;
    std::vector<float> data;
};

Rgba to_rgba(gdr_frame* frame, const char* layer, size_t w, size_t h) {
    const float* planar = nullptr;
    size_t channels = 0;
    CHECKED(gdr_frame_get_layer(frame, layer, &planar, &channels));
    if (!planar || channels != 3) throw std::runtime_error(std::string("no RGB layer ") + layer);
    Rgba out{w, h, std::vector<float>(w * h * 4, 1.0f)};
    for (size_t c = 0; c < 3; c++)
        for (size_t p = 0; p < w * h; p++) out.data[p * 4 + c] = planar[c * w * h + p];
    return out;
}

void write_pfm(const std::string& path, const Rgba& img) {
    std::FILE* f = std::fopen(path.c_str(), "wb");
    if (!f) throw std::runtime_error("cannot write " + path);
    std::fprintf(f, "PF\n%zu %zu\n-1.0\n", img.width, img.height);
    for (size_t y = img.height; y-- > 0;)
        for (size_t x = 0; x < img.width; x++)
            std::fwrite(&img.data[(y * img.width + x) * 4], sizeof(float), 3, f);
    std::fclose(f);
}

}  // namespace

int main(int argc, char** argv) try {
    if (argc != 3) {
        std::fprintf(stderr, "usage: %s FRAME.exr OUT_PREFIX\n", argv[0]);
        return 2;
    }
    gdr_context* raw_ctx = nullptr;
    CHECKED(gdr_context_new(&raw_ctx));
    Context ctx(raw_ctx);
    CHECKED(gdr_context_commit(ctx.get()));
    gdr_frame* raw_frame = nullptr;
    CHECKED(gdr_frame_read(argv[1], &raw_frame));
    Frame frame(raw_frame);
    size_t w = 0, h = 0;
    float spp = 0;
    CHECKED(gdr_frame_get_info(frame.get(), &w, &h, &spp));

    for (uint32_t m = 0; const char* method = gdr_method_name(m); m++) {
        Rgba color = to_rgba(frame.get(), "color", w, h);
        const Rgba dx = to_rgba(frame.get(), "dx", w, h);
        const Rgba dy = to_rgba(frame.get(), "dy", w, h);
        gdr_filter* raw_filter = nullptr;
        CHECKED(gdr_filter_new(ctx.get(), method, &raw_filter));
        Filter filter(raw_filter);
        const size_t px = 4 * sizeof(float);  // RGB read out of RGBA through the pixel stride
        CHECKED(gdr_filter_set_image(filter.get(), "color", color.data.data(), w, h, 3, px, 0));
        CHECKED(gdr_filter_set_image(filter.get(), "dx", dx.data.data(), w, h, 3, px, 0));
        CHECKED(gdr_filter_set_image(filter.get(), "dy", dy.data.data(), w, h, 3, px, 0));
        CHECKED(gdr_filter_set_image(filter.get(), "output", color.data.data(), w, h, 3, px, 0));
        CHECKED(gdr_filter_set_float(filter.get(), "spp", spp));
        CHECKED(gdr_filter_commit(filter.get()));
        CHECKED(gdr_filter_execute(filter.get()));
        const std::string path = std::string(argv[2]) + "_" + method + ".pfm";
        write_pfm(path, color);
        std::printf("%s: wrote %s (in place, RGBA)\n", method, path.c_str());
    }
    return 0;
} catch (const std::exception& e) {
    std::fprintf(stderr, "%s\n", e.what());
    return 1;
}
