/* Reconstructs a frame bundle with every method of the C API and writes one PFM per method.
 *
 *   reconstruct FRAME.exr OUT_PREFIX      -> OUT_PREFIX_l2.pfm, OUT_PREFIX_l1.pfm, ...
 *
 * The bundle is read through the API (gdr_frame_read); its planar layers are handed to the
 * filter without copies, and the filter is committed once and executed per method. */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "gdrecon.h"

static int fail(const char* what) {
    const char* message = "";
    gdr_error code = gdr_get_error(&message);
    fprintf(stderr, "%s: %s: %s\n", what, gdr_error_name(code), message);
    return 1;
}

#define TRY(call)                              \
    do {                                       \
        if ((call) != GDR_ERROR_NONE) return fail(#call); \
    } while (0)

/* PFM: little-endian RGB floats, rows bottom to top. */
static int write_pfm(const char* path, const float* rgb, size_t w, size_t h) {
    size_t y;
    FILE* f = fopen(path, "wb");
    if (!f) return 1;
    fprintf(f, "PF\n%zu %zu\n-1.0\n", w, h);
    for (y = h; y-- > 0;) fwrite(rgb + y * w * 3, sizeof(float), w * 3, f);
    return fclose(f) != 0;
}

static bool on_progress(void* user, double fraction) {
    (void)user;
    (void)fraction;
    return true; /* return false to cancel */
}

int main(int argc, char** argv) {
    static const char* const layers[] = {"color", "dx", "dy", "variance", "albedo", "normal", "depth"};
    gdr_context* ctx = NULL;
    gdr_frame* frame = NULL;
    size_t width, height, channels, i;
    float spp;
    float* out;
    uint32_t m;
    if (argc != 3) {
        fprintf(stderr, "usage: %s FRAME.exr OUT_PREFIX\n", argv[0]);
        return 2;
    }
    if (gdr_version() < GDR_VERSION) {
        fprintf(stderr, "libgdrecon is older than gdrecon.h\n");
        return 1;
    }
    TRY(gdr_context_new(&ctx));
    TRY(gdr_context_set_int(ctx, "threads", 0)); /* all cores */
    TRY(gdr_context_commit(ctx));
    TRY(gdr_frame_read(argv[1], &frame));
    TRY(gdr_frame_get_info(frame, &width, &height, &spp));
    printf("%s: %zu x %zu, %g spp\n", argv[1], width, height, spp);
    out = (float*)malloc(width * height * 3 * sizeof(float));
    if (!out) return 1;

    for (m = 0; gdr_method_name(m) != NULL; m++) {
        const char* method = gdr_method_name(m);
        const char* report = NULL;
        char path[4096];
        gdr_filter* filter = NULL;
        TRY(gdr_filter_new(ctx, method, &filter));
        for (i = 0; i < sizeof layers / sizeof layers[0]; i++) {
            const float* data = NULL;
            TRY(gdr_frame_get_layer(frame, layers[i], &data, &channels));
            if (data) TRY(gdr_filter_set_image_planar(filter, layers[i], data, width, height, channels, 0, 0));
        }
        TRY(gdr_filter_set_image(filter, "output", out, width, height, 3, 0, 0));
        /* alpha is the screened Poisson weight: only the Poisson methods have it. */
        if (strcmp(method, "l2") == 0 || strcmp(method, "l1") == 0)
            TRY(gdr_filter_set_float(filter, "alpha", 0.2f));
        TRY(gdr_filter_set_float(filter, "spp", spp));
        TRY(gdr_filter_set_progress_callback(filter, on_progress, NULL));
        TRY(gdr_filter_commit(filter));
        TRY(gdr_filter_execute(filter));
        TRY(gdr_filter_get_report(filter, &report));
        printf("%s", report);
        snprintf(path, sizeof path, "%s_%s.pfm", argv[2], method);
        if (write_pfm(path, out, width, height)) {
            fprintf(stderr, "cannot write %s\n", path);
            return 1;
        }
        printf("wrote %s\n", path);
        TRY(gdr_filter_release(&filter));
    }
    free(out);
    TRY(gdr_frame_release(&frame));
    TRY(gdr_context_release(&ctx));
    return 0;
}
