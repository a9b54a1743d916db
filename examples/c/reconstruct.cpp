// The same as reconstruct.c in C++, with the buffers a renderer would have: one interleaved
// RGBA float buffer per pass (copied here from the bundle), the result written in place into
// the colour buffer's RGB, alpha untouched. Through include/gdrecon.hpp: RAII handles, errors
// as gdr::Error exceptions.
//
//   reconstruct_cpp FRAME.exr OUT_PREFIX      -> OUT_PREFIX_l2.pfm, OUT_PREFIX_l1.pfm, ...
#include <cstdio>
#include <stdexcept>
#include <string>
#include <vector>

#include "gdrecon.hpp"

namespace {

// A render pass as an interleaved RGBA buffer.
struct Rgba {
    size_t width = 0, height = 0;
    std::vector<float> data;
};

Rgba to_rgba(const gdr::Frame& frame, const char* layer) {
    const gdr::Frame::Layer planar = frame.layer(layer);
    if (!planar || planar.channels != 3) throw std::runtime_error(std::string("no RGB layer ") + layer);
    const size_t w = frame.width(), h = frame.height();
    Rgba out{w, h, std::vector<float>(w * h * 4, 1.0f)};
    for (size_t c = 0; c < 3; c++)
        for (size_t p = 0; p < w * h; p++) out.data[p * 4 + c] = planar.data[c * w * h + p];
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
    gdr::Context ctx;
    ctx.commit();
    const gdr::Frame frame(argv[1]);
    const size_t w = frame.width(), h = frame.height();

    for (const std::string& method : gdr::methods()) {
        Rgba color = to_rgba(frame, "color");
        const Rgba dx = to_rgba(frame, "dx");
        const Rgba dy = to_rgba(frame, "dy");
        gdr::Filter filter(ctx, method);
        const size_t px = 4 * sizeof(float);  // RGB read out of RGBA through the pixel stride
        filter.setImage("color", color.data.data(), w, h, 3, px);
        filter.setImage("dx", dx.data.data(), w, h, 3, px);
        filter.setImage("dy", dy.data.data(), w, h, 3, px);
        // The feature passes, when the bundle has them (the combiner needs all three).
        std::vector<Rgba> features;
        features.reserve(3);
        for (const char* layer : {"variance", "albedo", "normal"}) {
            const gdr::Frame::Layer planar = frame.layer(layer);
            if (!planar || planar.channels != 3) continue;
            features.push_back(to_rgba(frame, layer));
            filter.setImage(layer, features.back().data.data(), w, h, 3, px);
        }
        filter.setImage("output", color.data.data(), w, h, 3, px);
        filter.set("spp", frame.spp());
        filter.commit();
        filter.execute();
        const std::string path = std::string(argv[2]) + "_" + method + ".pfm";
        write_pfm(path, color);
        std::printf("%s: wrote %s (in place, RGBA)\n", method.c_str(), path.c_str());
    }
    return 0;
} catch (const std::exception& e) {
    std::fprintf(stderr, "%s\n", e.what());
    return 1;
}
