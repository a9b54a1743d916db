/* Tests of the gdrecon C API, compiled as C99 and as C++ (tests/c/run.sh):
 *   test_capi REF_DIR [SAMPLE.exr]
 * REF_DIR holds frame.bin (97 x 61 synthetic frame, 7 interleaved layers) and ref_*.bin, the
 * Rust API's outputs for it (tests/capi.rs, write_reference_for_c). Results must match them
 * bit for bit, whatever the layout. Every error case has its own status. The last line is
 * "N passed, N failed". Set GDR_TEST_NO_TIMING=1 to skip the latency bound (valgrind). */
#define _POSIX_C_SOURCE 199309L
#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "check.h"
#include "gdrecon.h"

#ifdef __cplusplus
#define STATIC_ASSERT(c, m) static_assert(c, m)
#else
#define STATIC_ASSERT(c, m) _Static_assert(c, m)
#endif

STATIC_ASSERT(sizeof(gdr_error) == 4, "gdr_error is 32 bits");
STATIC_ASSERT(sizeof(gdr_log_level) == 4, "gdr_log_level is 32 bits");
STATIC_ASSERT(GDR_VERSION == GDR_VERSION_MAJOR * 10000 + GDR_VERSION_MINOR * 100 + GDR_VERSION_PATCH,
              "version macros agree");

/* ---- the reference frame ------------------------------------------------------------- */

enum { NLAYERS = 7 };
static const char* const layer_names[NLAYERS] = {"color", "dx", "dy", "variance",
                                                 "albedo", "normal", "depth"};
static const size_t layer_channels[NLAYERS] = {3, 3, 3, 3, 3, 3, 1};
static size_t W, H;
static float* layers[NLAYERS]; /* packed interleaved */

static float* read_floats(const char* dir, const char* name, size_t skip_bytes, size_t count) {
    char path[4096];
    FILE* f;
    float* data = (float*)malloc(count * sizeof(float));
    snprintf(path, sizeof path, "%s/%s", dir, name);
    f = fopen(path, "rb");
    if (!f || !data || fseek(f, (long)skip_bytes, SEEK_SET) != 0 ||
        fread(data, sizeof(float), count, f) != count) {
        fprintf(stderr, "cannot read %s\n", path);
        exit(2);
    }
    fclose(f);
    return data;
}

static void load_frame(const char* dir) {
    char path[4096];
    uint32_t size[2];
    size_t offset = 8;
    int i;
    FILE* f;
    snprintf(path, sizeof path, "%s/frame.bin", dir);
    f = fopen(path, "rb");
    if (!f || fread(size, 4, 2, f) != 2) {
        fprintf(stderr, "cannot read %s\n", path);
        exit(2);
    }
    fclose(f);
    W = size[0];
    H = size[1];
    for (i = 0; i < NLAYERS; i++) {
        layers[i] = read_floats(dir, "frame.bin", offset, W * H * layer_channels[i]);
        offset += W * H * layer_channels[i] * sizeof(float);
    }
}

static int same_bits(const float* a, const float* b, size_t n) {
    return memcmp(a, b, n * sizeof(float)) == 0;
}

static gdr_context* new_context(void) {
    gdr_context* ctx = NULL;
    OK(gdr_context_new(&ctx));
    OK(gdr_context_set_int(ctx, "threads", 2));
    OK(gdr_context_commit(ctx));
    return ctx;
}

static void set_packed_inputs(gdr_filter* f, int count) {
    int i;
    for (i = 0; i < count; i++)
        OK(gdr_filter_set_image(f, layer_names[i], layers[i], W, H, layer_channels[i], 0, 0));
}

/* ---- tests --------------------------------------------------------------------------- */

static void test_version(void) {
    CHECK(gdr_version() == GDR_VERSION);
    CHECK(strcmp(gdr_method_name(0), "l2") == 0);
    CHECK(strcmp(gdr_method_name(1), "l1") == 0);
    CHECK(gdr_method_name(1000) == NULL);
    CHECK(strcmp(gdr_error_name(GDR_ERROR_CANCELLED), "GDR_ERROR_CANCELLED") == 0);
    CHECK(strcmp(gdr_error_name(9999), "GDR_ERROR_?") == 0);
}

/* Every method's parameters, listed and set from C as a generic settings UI would. */
static void test_param_listing(gdr_context* ctx) {
    gdr_param_info info;
    size_t count = 0, k;
    uint32_t m;
    int saw_guide = 0;
    for (m = 0; gdr_method_name(m) != NULL; m++) {
        const char* method = gdr_method_name(m);
        gdr_filter* f = NULL;
        OK(gdr_method_param_count(method, &count));
        CHECK(count >= 1);
        OK(gdr_filter_new(ctx, method, &f));
        for (k = 0; k < count; k++) {
            info.size = sizeof info;
            OK(gdr_method_param(method, k, &info));
            CHECK(info.name != NULL && info.name[0] != '\0' && info.doc[0] != '\0');
            CHECK(info.min <= info.default_value && info.default_value <= info.max);
            if (info.kind == GDR_PARAM_CHOICE) {
                CHECK(info.choices[0] != '\0');
                if (strcmp(info.name, "guide") == 0) {
                    saw_guide = 1;
                    CHECK(strcmp(info.choices, "rdfc,l1,none,prior") == 0);
                }
            }
            switch (info.kind) {
            case GDR_PARAM_FLOAT:
                OK(gdr_filter_set_float(f, info.name, (float)info.default_value));
                break;
            case GDR_PARAM_CHOICE: /* set by its index */
            case GDR_PARAM_INT:
                OK(gdr_filter_set_int(f, info.name, (int32_t)info.default_value));
                EXPECT(gdr_filter_set_int(f, info.name, (int32_t)info.max + 1),
                       GDR_ERROR_INVALID_ARGUMENT);
                break;
            case GDR_PARAM_BOOL:
                OK(gdr_filter_set_bool(f, info.name, info.default_value != 0.0));
                break;
            default:
                CHECK(!"unknown parameter kind");
            }
        }
        EXPECT(gdr_method_param(method, count, &info), GDR_ERROR_INVALID_ARGUMENT);
        OK(gdr_filter_release(&f));
    }
    CHECK(saw_guide);
    info.size = 4; /* an older, smaller struct than this library's */
    EXPECT(gdr_method_param("l1", 0, &info), GDR_ERROR_INVALID_ARGUMENT);
    EXPECT(gdr_method_param_count("nope", &count), GDR_ERROR_INVALID_ARGUMENT);
}

/* Packed inputs, each method, against the Rust API's output. */
static void test_bit_for_bit(gdr_context* ctx, const char* dir) {
    const char* methods[3] = {"l2", "l1", "l1"};
    const char* refs[3] = {"ref_l2.bin", "ref_l1.bin", "ref_l1_custom.bin"};
    int m;
    for (m = 0; m < 3; m++) {
        gdr_filter* f = NULL;
        float* ref = read_floats(dir, refs[m], 0, W * H * 3);
        float* out = (float*)calloc(W * H * 3, sizeof(float));
        OK(gdr_filter_new(ctx, methods[m], &f));
        if (m == 2) {
            float alpha = 0;
            OK(gdr_filter_set_float(f, "alpha", 0.5f));
            OK(gdr_filter_set_int(f, "reweight_steps", 6));
            OK(gdr_filter_set_int(f, "cg_iterations", 5));
            OK(gdr_filter_get_float(f, "alpha", &alpha));
            CHECK(alpha == 0.5f);
        }
        set_packed_inputs(f, NLAYERS);
        OK(gdr_filter_set_image(f, "output", out, W, H, 3, 0, 0));
        OK(gdr_filter_commit(f));
        OK(gdr_filter_execute(f));
        CHECK(same_bits(out, ref, W * H * 3));
        memset(out, 0, W * H * 3 * sizeof(float));
        OK(gdr_filter_execute(f)); /* again, same buffers */
        CHECK(same_bits(out, ref, W * H * 3));
        OK(gdr_filter_release(&f));
        CHECK(f == NULL);
        free(out);
        free(ref);
    }
}

/* A caller's prior (image "prior") is used as given, and presets are set by name. Nothing here
 * loads Open Image Denoise (the prior is given), so it runs under valgrind too. */
static void test_prior(gdr_context* ctx) {
    float* out = (float*)calloc(W * H * 3, sizeof(float));
    gdr_filter* f = NULL;
    const char* msg;
    OK(gdr_filter_new(ctx, "l1", &f));
    msg = EXPECT(gdr_filter_set_preset(f, "nope"), GDR_ERROR_INVALID_ARGUMENT);
    CONTAINS(msg, "fast, published, prior");
    OK(gdr_filter_set_preset(f, "prior"));
    OK(gdr_filter_release(&f));
    OK(gdr_filter_new(ctx, "prior", &f));
    set_packed_inputs(f, 3);
    /* Any RGB image will do as the prior: here the base colour itself. */
    OK(gdr_filter_set_image(f, "prior", layers[0], W, H, 3, 0, 0));
    OK(gdr_filter_set_image(f, "output", out, W, H, 3, 0, 0));
    OK(gdr_filter_commit(f));
    OK(gdr_filter_execute(f));
    CHECK(same_bits(out, layers[0], W * H * 3));
    OK(gdr_filter_release(&f));
    free(out);
}

/* "max_memory_mb" sizes tiles before it refuses: a 1280 x 768 prior is estimated at 676 MiB
 * (OIDN's scratch 544 of it) and at 644 MiB with OIDN's scratch at its floor of 512, so at
 * 665 its commit fits (it was refused before the fifty-eighth session) and at 600 it is
 * refused in one line naming the limit. Commit only: nothing is denoised. */
static void test_memory_budget(void) {
    const size_t w = 1280, h = 768;
    float* planes[4];
    const char* names[4] = {"color", "dx", "dy", "output"};
    const int limits[2] = {665, 600};
    int i, k;
    for (i = 0; i < 4; i++) planes[i] = (float*)calloc(w * h * 3, sizeof(float));
    for (k = 0; k < 2; k++) {
        gdr_context* ctx = NULL;
        gdr_filter* f = NULL;
        OK(gdr_context_new(&ctx));
        OK(gdr_context_set_int(ctx, "threads", 1));
        OK(gdr_context_set_int(ctx, "max_memory_mb", limits[k]));
        OK(gdr_context_commit(ctx));
        OK(gdr_filter_new(ctx, "prior", &f));
        for (i = 0; i < 4; i++) OK(gdr_filter_set_image(f, names[i], planes[i], w, h, 3, 0, 0));
        if (k == 0) {
            OK(gdr_filter_commit(f));
        } else {
            const char* msg = EXPECT(gdr_filter_commit(f), GDR_ERROR_OUT_OF_MEMORY);
            CONTAINS(msg, "needs about 644 MiB, more than max_memory_mb = 600");
        }
        OK(gdr_filter_release(&f));
        OK(gdr_context_release(&ctx));
    }
    for (i = 0; i < 4; i++) free(planes[i]);
}

/* RGBA with padded rows, planar, in place, and all passes in one buffer: same bits. */
static void test_layouts(gdr_context* ctx, const char* dir) {
    size_t row = W * 4 + 8; /* floats per padded RGBA row */
    size_t x, y, c, i;
    float* ref = read_floats(dir, "ref_l2.bin", 0, W * H * 3);
    float* rgba[3];
    float* planes[3];
    float* planar_out = (float*)calloc(3 * W * H, sizeof(float));
    float* big = (float*)calloc(W * H * 12, sizeof(float));
    float* got = (float*)malloc(W * H * 3 * sizeof(float));
    int alpha_untouched = 1;
    gdr_filter* f = NULL;
    OK(gdr_filter_new(ctx, "l2", &f));

    for (i = 0; i < 3; i++) {
        rgba[i] = (float*)malloc(row * H * sizeof(float));
        planes[i] = (float*)malloc(3 * W * H * sizeof(float));
        for (y = 0; y < H; y++)
            for (x = 0; x < W; x++) {
                for (c = 0; c < 3; c++) {
                    float v = layers[i][(y * W + x) * 3 + c];
                    rgba[i][y * row + x * 4 + c] = v;
                    planes[i][c * W * H + y * W + x] = v;
                    big[(y * W + x) * 12 + i * 3 + c] = v;
                }
                rgba[i][y * row + x * 4 + 3] = 7.0f; /* alpha */
            }
        OK(gdr_filter_set_image(f, layer_names[i], rgba[i], W, H, 3, 16, row * 4));
    }
    /* In place: the output is exactly the color view. */
    OK(gdr_filter_set_image(f, "output", rgba[0], W, H, 3, 16, row * 4));
    OK(gdr_filter_commit(f));
    OK(gdr_filter_execute(f));
    for (y = 0; y < H; y++)
        for (x = 0; x < W; x++) {
            for (c = 0; c < 3; c++) got[(y * W + x) * 3 + c] = rgba[0][y * row + x * 4 + c];
            alpha_untouched &= rgba[0][y * row + x * 4 + 3] == 7.0f;
        }
    CHECK(same_bits(got, ref, W * H * 3));
    CHECK(alpha_untouched);

    for (i = 0; i < 3; i++) OK(gdr_filter_set_image_planar(f, layer_names[i], planes[i], W, H, 3, 0, 0));
    OK(gdr_filter_set_image_planar(f, "output", planar_out, W, H, 3, 0, 0));
    OK(gdr_filter_commit(f));
    OK(gdr_filter_execute(f));
    for (y = 0; y < H; y++)
        for (x = 0; x < W; x++)
            for (c = 0; c < 3; c++) got[(y * W + x) * 3 + c] = planar_out[c * W * H + y * W + x];
    CHECK(same_bits(got, ref, W * H * 3));

    /* One render buffer of 12 floats per pixel: color, dx, dy, then the output. */
    for (i = 0; i < 3; i++) OK(gdr_filter_set_image(f, layer_names[i], big + 3 * i, W, H, 3, 48, 0));
    OK(gdr_filter_set_image(f, "output", big + 9, W, H, 3, 48, 0));
    OK(gdr_filter_commit(f));
    OK(gdr_filter_execute(f));
    for (i = 0; i < W * H; i++)
        for (c = 0; c < 3; c++) got[i * 3 + c] = big[i * 12 + 9 + c];
    CHECK(same_bits(got, ref, W * H * 3));

    OK(gdr_filter_release(&f));
    for (i = 0; i < 3; i++) {
        free(rgba[i]);
        free(planes[i]);
    }
    free(planar_out);
    free(big);
    free(got);
    free(ref);
}

static void test_errors(gdr_context* ctx) {
    gdr_context* raw = NULL;
    gdr_filter* f = NULL;
    gdr_frame* frame = NULL;
    float* out = (float*)calloc(W * H * 3, sizeof(float));
    float* dx = (float*)malloc(W * H * 3 * sizeof(float));
    float* nan_color = (float*)malloc(W * H * 3 * sizeof(float));
    const char* m;
    memcpy(dx, layers[1], W * H * 3 * sizeof(float));
    memcpy(nan_color, layers[0], W * H * 3 * sizeof(float));
    nan_color[5] = (float)NAN;

    /* Null pointers. */
    EXPECT(gdr_context_new(NULL), GDR_ERROR_NULL_POINTER);
    EXPECT(gdr_context_commit(NULL), GDR_ERROR_NULL_POINTER);
    EXPECT(gdr_context_set_int(ctx, NULL, 1), GDR_ERROR_NULL_POINTER);
    EXPECT(gdr_filter_execute(NULL), GDR_ERROR_NULL_POINTER);
    EXPECT(gdr_filter_commit(NULL), GDR_ERROR_NULL_POINTER);
    EXPECT(gdr_filter_set_float(NULL, "alpha", 1.0f), GDR_ERROR_NULL_POINTER);
    EXPECT(gdr_filter_release(NULL), GDR_ERROR_NULL_POINTER);
    OK(gdr_filter_release(&f)); /* releasing NULL is a no-op */
    m = EXPECT(gdr_filter_new(NULL, "l2", &f), GDR_ERROR_NULL_POINTER);
    CONTAINS(m, "context");
    CHECK(f == NULL);
    EXPECT(gdr_get_error(NULL), GDR_ERROR_NONE);

    /* Unknown method: the message lists the valid ones. */
    m = EXPECT(gdr_filter_new(ctx, "gradnot", &f), GDR_ERROR_INVALID_ARGUMENT);
    CONTAINS(m, "l2");
    CONTAINS(m, "l1");

    /* Wrong order on contexts. */
    OK(gdr_context_new(&raw));
    EXPECT(gdr_filter_new(raw, "l2", &f), GDR_ERROR_INVALID_OPERATION);
    EXPECT(gdr_context_set_int(raw, "threads", -2), GDR_ERROR_INVALID_ARGUMENT);
    EXPECT(gdr_context_set_int(raw, "log_level", 9), GDR_ERROR_INVALID_ARGUMENT);
    EXPECT(gdr_context_set_string(raw, "nope", "x"), GDR_ERROR_INVALID_ARGUMENT);
    OK(gdr_context_set_string(raw, "model_path", "/models/gradnet.onnx"));
    OK(gdr_context_commit(raw));
    EXPECT(gdr_context_commit(raw), GDR_ERROR_INVALID_OPERATION);
    EXPECT(gdr_context_set_int(raw, "threads", 1), GDR_ERROR_INVALID_OPERATION);
    EXPECT(gdr_context_set_string(raw, "onnxruntime_path", "/x.so"), GDR_ERROR_INVALID_OPERATION);
    OK(gdr_context_retain(raw));
    {
        gdr_context* second = raw;
        OK(gdr_context_release(&second));
        CHECK(second == NULL);
    }
    OK(gdr_context_release(&raw));
    CHECK(raw == NULL);

    OK(gdr_filter_new(ctx, "l1", &f));
    /* Parameters: unknown (lists the valid ones), wrong type, out of range. */
    m = EXPECT(gdr_filter_set_float(f, "alfa", 0.1f), GDR_ERROR_INVALID_ARGUMENT);
    CONTAINS(m, "alpha");
    CONTAINS(m, "cg_iterations");
    m = EXPECT(gdr_filter_set_bool(f, "alpha", true), GDR_ERROR_INVALID_ARGUMENT);
    CONTAINS(m, "gdr_filter_set_float");
    EXPECT(gdr_filter_set_int(f, "reweight_steps", -1), GDR_ERROR_INVALID_ARGUMENT);
    EXPECT(gdr_filter_set_float(f, "spp", -4.0f), GDR_ERROR_INVALID_ARGUMENT);

    /* Wrong order on filters. */
    EXPECT(gdr_filter_execute(f), GDR_ERROR_INVALID_OPERATION);
    m = EXPECT(gdr_filter_commit(f), GDR_ERROR_INVALID_OPERATION);
    CONTAINS(m, "'color'");

    /* Image views. */
    EXPECT(gdr_filter_set_image(f, "colour", layers[0], W, H, 3, 0, 0), GDR_ERROR_INVALID_ARGUMENT);
    m = EXPECT(gdr_filter_set_image(f, "dx", NULL, W, H, 3, 0, 0), GDR_ERROR_NULL_POINTER);
    CONTAINS(m, "'dx'");
    m = EXPECT(gdr_filter_set_image(f, "color", layers[0], W, H, 4, 0, 0), GDR_ERROR_INVALID_IMAGE);
    CONTAINS(m, "'color'");
    EXPECT(gdr_filter_set_image(f, "depth", layers[0], W, H, 3, 0, 0), GDR_ERROR_INVALID_IMAGE);
    EXPECT(gdr_filter_set_image(f, "color", (const float*)((const char*)layers[0] + 2), W, H, 3, 0, 0),
           GDR_ERROR_INVALID_IMAGE);
    EXPECT(gdr_filter_set_image(f, "color", layers[0], W, H, 3, 13, 0), GDR_ERROR_INVALID_IMAGE);
    m = EXPECT(gdr_filter_set_image(f, "color", layers[0], W, H, 3, 8, 0), GDR_ERROR_INVALID_IMAGE);
    CONTAINS(m, "overlap");
    EXPECT(gdr_filter_set_image(f, "color", layers[0], 0, H, 3, 0, 0), GDR_ERROR_INVALID_IMAGE);
    EXPECT(gdr_filter_set_image(f, "color", layers[0], SIZE_MAX / 8, H, 3, 0, 0), GDR_ERROR_INVALID_IMAGE);
    set_packed_inputs(f, NLAYERS);
    OK(gdr_filter_set_image(f, "output", out, W, H - 1, 3, 0, 0));
    m = EXPECT(gdr_filter_commit(f), GDR_ERROR_INVALID_IMAGE);
    CONTAINS(m, "'output'");
    OK(gdr_filter_unset_image(f, "output"));
    m = EXPECT(gdr_filter_commit(f), GDR_ERROR_INVALID_OPERATION);
    CONTAINS(m, "'output'");
    OK(gdr_filter_set_image(f, "albedo", layers[4], W - 1, H, 3, 0, 0));
    OK(gdr_filter_set_image(f, "output", out, W, H, 3, 0, 0));
    m = EXPECT(gdr_filter_commit(f), GDR_ERROR_INVALID_IMAGE);
    CONTAINS(m, "'albedo'");
    OK(gdr_filter_unset_image(f, "albedo"));

    /* Output partially overlapping an input (one pixel off): an error. Exactly an input: fine. */
    OK(gdr_filter_set_image(f, "dx", dx, W, H - 1, 3, 0, 0));
    OK(gdr_filter_set_image(f, "output", dx + 3, W, H - 1, 3, 0, 0));
    OK(gdr_filter_set_image(f, "color", layers[0], W, H - 1, 3, 0, 0));
    OK(gdr_filter_set_image(f, "dy", layers[2], W, H - 1, 3, 0, 0));
    OK(gdr_filter_unset_image(f, "variance"));
    OK(gdr_filter_unset_image(f, "normal"));
    OK(gdr_filter_unset_image(f, "depth"));
    m = EXPECT(gdr_filter_commit(f), GDR_ERROR_OVERLAP);
    CONTAINS(m, "'dx'");
    OK(gdr_filter_set_image(f, "output", dx, W, H - 1, 3, 0, 0));
    OK(gdr_filter_commit(f));
    OK(gdr_filter_execute(f));

    /* Out-of-range parameters are refused when set, with the accepted range; the filter keeps
     * its value and still executes. */
    m = EXPECT(gdr_filter_set_float(f, "alpha", -1.0f), GDR_ERROR_INVALID_ARGUMENT);
    CONTAINS(m, "alpha is -1, expected a float in (0, 10000]");
    {
        float alpha = 0.0f;
        OK(gdr_filter_get_float(f, "alpha", &alpha));
        CHECK(alpha == 0.2f);
    }
    OK(gdr_filter_execute(f));
    OK(gdr_filter_set_float(f, "alpha", 0.2f));

    /* NaN: replaced by default, an error in strict mode. */
    set_packed_inputs(f, 3);
    OK(gdr_filter_set_image(f, "color", nan_color, W, H, 3, 0, 0));
    OK(gdr_filter_set_image(f, "output", out, W, H, 3, 0, 0));
    OK(gdr_filter_commit(f));
    OK(gdr_filter_execute(f));
    {
        size_t i;
        int finite = 1;
        for (i = 0; i < W * H * 3; i++) finite &= isfinite(out[i]) ? 1 : 0;
        CHECK(finite);
    }
    OK(gdr_filter_set_bool(f, "strict", true));
    OK(gdr_filter_commit(f));
    m = EXPECT(gdr_filter_execute(f), GDR_ERROR_INVALID_INPUT);
    CONTAINS(m, "color");

    /* A panic inside the library comes back as a status, and the filter still works. */
    m = EXPECT(gdr_filter_set_bool(f, "internal_test_panic", true), GDR_ERROR_UNKNOWN);
    CONTAINS(m, "panic");
    OK(gdr_filter_set_bool(f, "strict", false));
    OK(gdr_filter_commit(f));
    OK(gdr_filter_execute(f));
    OK(gdr_filter_release(&f));

    /* Files. */
    EXPECT(gdr_frame_read("/nonexistent/frame.exr", &frame), GDR_ERROR_IO);
    CHECK(frame == NULL);
    EXPECT(gdr_frame_read(NULL, &frame), GDR_ERROR_NULL_POINTER);
    free(out);
    free(dx);
    free(nan_color);
}

/* ---- cancellation ---------------------------------------------------------------------- */

static double now_seconds(void) {
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return (double)t.tv_sec + 1e-9 * (double)t.tv_nsec;
}

struct cancel_state {
    int calls;
    double cancelled_at;
    gdr_filter* filter;
    gdr_error reentrant;
    int use_cancel_call;
};

static bool on_progress(void* user, double fraction) {
    struct cancel_state* s = (struct cancel_state*)user;
    (void)fraction;
    s->calls++;
    if (s->calls == 1) {
        /* Calls on the same filter from its own callback fail rather than deadlock. */
        s->reentrant = gdr_filter_set_float(s->filter, "alpha", 0.3f);
        return true;
    }
    s->cancelled_at = now_seconds();
    if (s->use_cancel_call) {
        gdr_filter_cancel(s->filter);
        return true;
    }
    return false;
}

static void test_cancellation(gdr_context* ctx) {
    const size_t w = 1280, h = 720;
    float* img = (float*)malloc(w * h * 3 * sizeof(float));
    float* color = (float*)malloc(w * h * 3 * sizeof(float));
    float* gx = (float*)calloc(w * h * 3, sizeof(float));
    float* gy = (float*)calloc(w * h * 3, sizeof(float));
    float* out = (float*)calloc(w * h * 3, sizeof(float));
    uint32_t rng = 12345;
    size_t x, y, c, i;
    int round, untouched = 1;
    gdr_filter* f = NULL;
    const char* no_timing = getenv("GDR_TEST_NO_TIMING");
    for (y = 0; y < h; y++)
        for (x = 0; x < w; x++)
            for (c = 0; c < 3; c++)
                img[(y * w + x) * 3 + c] = 0.5f + 0.4f * (float)sin(0.01 * (double)(x + 2 * y + 50 * c)) +
                                           (((x / 64) + (y / 64)) % 2 ? 0.3f : 0.0f);
    for (i = 0; i < w * h * 3; i++) {
        rng = rng * 1664525u + 1013904223u;
        color[i] = img[i] + 0.2f * ((float)(rng >> 8) / 16777216.0f - 0.5f);
    }
    for (y = 0; y < h; y++)
        for (x = 0; x < w; x++)
            for (c = 0; c < 3; c++) {
                size_t p = (y * w + x) * 3 + c;
                if (x + 1 < w) gx[p] = img[p + 3] - img[p];
                if (y + 1 < h) gy[p] = img[p + w * 3] - img[p];
            }
    OK(gdr_filter_new(ctx, "l1", &f));
    OK(gdr_filter_set_image(f, "color", color, w, h, 3, 0, 0));
    OK(gdr_filter_set_image(f, "dx", gx, w, h, 3, 0, 0));
    OK(gdr_filter_set_image(f, "dy", gy, w, h, 3, 0, 0));
    OK(gdr_filter_set_image(f, "output", out, w, h, 3, 0, 0));
    OK(gdr_filter_commit(f));
    for (round = 0; round < 2; round++) {
        struct cancel_state s;
        double returned, latency_ms;
        s.calls = 0;
        s.cancelled_at = 0;
        s.filter = f;
        s.reentrant = GDR_ERROR_NONE;
        s.use_cancel_call = round;
        OK(gdr_filter_set_progress_callback(f, on_progress, &s));
        EXPECT(gdr_filter_execute(f), GDR_ERROR_CANCELLED);
        returned = now_seconds();
        latency_ms = 1e3 * (returned - s.cancelled_at);
        printf("cancellation latency (1280x720, l1, %s): %.2f ms\n",
               round ? "gdr_filter_cancel" : "callback returns false", latency_ms);
        CHECK(s.calls == 2);
        CHECK(s.reentrant == GDR_ERROR_INVALID_OPERATION);
        if (!no_timing) CHECK(latency_ms < 1000.0); /* ~2 ms idle; generous under load */
    }
    for (i = 0; i < w * h * 3; i++) untouched &= out[i] == 0.0f;
    CHECK(untouched); /* a cancelled execute leaves the output alone */
    OK(gdr_filter_set_progress_callback(f, NULL, NULL));
    OK(gdr_filter_release(&f));
    free(img);
    free(color);
    free(gx);
    free(gy);
    free(out);
}

/* ---- logging and bundles --------------------------------------------------------------- */

static int log_lines[5];

static void on_log(void* user, uint32_t level, const char* message) {
    (void)user;
    if (level < 5 && message && message[0]) log_lines[level]++;
}

static void test_frame_and_log(const char* sample) {
    gdr_context* ctx = NULL;
    gdr_frame* frame = NULL;
    gdr_filter* f = NULL;
    size_t w = 0, h = 0, ch = 0;
    float spp = -1;
    const float* data = NULL;
    const char* report = NULL;
    float* out;
    int i;
    OK(gdr_context_new(&ctx));
    OK(gdr_context_set_log_callback(ctx, on_log, NULL));
    OK(gdr_context_set_int(ctx, "log_level", GDR_LOG_DEBUG));
    OK(gdr_context_commit(ctx));
    OK(gdr_frame_read(sample, &frame));
    OK(gdr_frame_get_info(frame, &w, &h, &spp));
    CHECK(w > 0 && h > 0 && spp > 0);
    OK(gdr_frame_get_layer(frame, "normal", &data, &ch));
    CHECK(data != NULL && ch == 3);
    OK(gdr_frame_get_layer(frame, "depth", &data, &ch));
    CHECK(data != NULL && ch == 1);
    EXPECT(gdr_frame_get_layer(frame, "colour", &data, &ch), GDR_ERROR_INVALID_ARGUMENT);
    OK(gdr_filter_new(ctx, "l1", &f));
    for (i = 0; i < NLAYERS; i++) {
        OK(gdr_frame_get_layer(frame, layer_names[i], &data, &ch));
        if (data) OK(gdr_filter_set_image_planar(f, layer_names[i], data, w, h, ch, 0, 0));
    }
    out = (float*)calloc(w * h * 3, sizeof(float));
    OK(gdr_filter_set_float(f, "spp", spp));
    OK(gdr_filter_set_image(f, "output", out, w, h, 3, 0, 0));
    OK(gdr_filter_commit(f));
    OK(gdr_filter_execute(f));
    OK(gdr_filter_get_report(f, &report));
    CONTAINS(report, "method l1");
    CHECK(log_lines[GDR_LOG_INFO] == 1);  /* the report */
    CHECK(log_lines[GDR_LOG_DEBUG] >= 2); /* context commit, planning */
    EXPECT(gdr_filter_set_float(f, "nope", 1.0f), GDR_ERROR_INVALID_ARGUMENT);
    CHECK(log_lines[GDR_LOG_ERROR] == 1); /* failures are logged too */
    OK(gdr_filter_release(&f));
    OK(gdr_frame_release(&frame));
    CHECK(frame == NULL);
    OK(gdr_context_release(&ctx));
    free(out);
}

/* GradNet through the C API: the runtime is found by the library's discovery (or the
 * context's "onnxruntime_path" when ORT_DYLIB_PATH names it), parameters round-trip, the
 * output is finite and close to the input's brightness, and a missing model is an I/O
 * error. GDR_TEST_EXPECT_ORT_DIR: the report must name a runtime in that directory (run.sh
 * uses it to check the "next to the library" discovery step). */
static void test_gradnet(const char* sample) {
    gdr_context* ctx = NULL;
    gdr_frame* frame = NULL;
    gdr_filter* f = NULL;
    size_t w = 0, h = 0, ch = 0, n, k;
    float spp = 0;
    const float* data = NULL;
    const float* color = NULL;
    const char* report = NULL;
    const char* msg;
    const char* ort_path = getenv("ORT_DYLIB_PATH");
    const char* expect_dir = getenv("GDR_TEST_EXPECT_ORT_DIR");
    float* out;
    double sum_in = 0, sum_out = 0;
    int finite = 1, tile = 0, i;
    bool bias = false;
    OK(gdr_context_new(&ctx));
    OK(gdr_context_set_int(ctx, "threads", 2));
    if (ort_path && !expect_dir) OK(gdr_context_set_string(ctx, "onnxruntime_path", ort_path));
    OK(gdr_context_commit(ctx));
    OK(gdr_frame_read(sample, &frame));
    OK(gdr_frame_get_info(frame, &w, &h, &spp));
    OK(gdr_filter_new(ctx, "gradnet", &f));
    OK(gdr_filter_set_int(f, "whole_pixels", 0)); /* tile even this small frame */
    OK(gdr_filter_set_int(f, "tile_pixels", 232 * 184));
    OK(gdr_filter_get_int(f, "tile_pixels", &tile));
    CHECK(tile == 232 * 184);
    OK(gdr_filter_get_bool(f, "bias_correction", &bias));
    CHECK(bias);
    msg = EXPECT(gdr_filter_set_float(f, "alpha", 0.2f), GDR_ERROR_INVALID_ARGUMENT);
    CONTAINS(msg, "tile_pixels");
    for (i = 0; i < NLAYERS; i++) {
        OK(gdr_frame_get_layer(frame, layer_names[i], &data, &ch));
        if (data) OK(gdr_filter_set_image_planar(f, layer_names[i], data, w, h, ch, 0, 0));
    }
    OK(gdr_frame_get_layer(frame, "color", &color, &ch));
    out = (float*)calloc(w * h * 3, sizeof(float));
    OK(gdr_filter_set_image(f, "output", out, w, h, 3, 0, 0));
    OK(gdr_filter_commit(f));
    OK(gdr_filter_execute(f));
    OK(gdr_filter_get_report(f, &report));
    CONTAINS(report, "method gradnet");
    CONTAINS(report, "4 tile(s)");
    if (expect_dir) CONTAINS(report, expect_dir);
    n = w * h;
    for (k = 0; k < 3 * n; k++) {
        if (!isfinite(out[k])) finite = 0;
        sum_out += out[k];
    }
    for (k = 0; k < 3 * n; k++) sum_in += color[k]; /* planar colour */
    CHECK(finite);
    CHECK(fabs(sum_out / sum_in - 1.0) < 0.05); /* the bias correction keeps the mean */
    OK(gdr_filter_release(&f));
    OK(gdr_context_release(&ctx));

    /* A model path that does not exist fails at commit, with the path in the message. */
    OK(gdr_context_new(&ctx));
    OK(gdr_context_set_string(ctx, "model_path", "/nonexistent/gradnet.onnx"));
    OK(gdr_context_commit(ctx));
    OK(gdr_filter_new(ctx, "gradnet", &f));
    for (i = 0; i < 3; i++) {
        OK(gdr_frame_get_layer(frame, layer_names[i], &data, &ch));
        OK(gdr_filter_set_image_planar(f, layer_names[i], data, w, h, ch, 0, 0));
    }
    OK(gdr_filter_set_image(f, "output", out, w, h, 3, 0, 0));
    msg = EXPECT(gdr_filter_commit(f), GDR_ERROR_IO);
    CONTAINS(msg, "/nonexistent/gradnet.onnx");
    OK(gdr_filter_release(&f));
    OK(gdr_context_release(&ctx));
    OK(gdr_frame_release(&frame));
    free(out);
}

int main(int argc, char** argv) {
    gdr_context* ctx;
    int i;
    if (argc < 2) {
        fprintf(stderr, "usage: %s REF_DIR [SAMPLE.exr]\n", argv[0]);
        return 2;
    }
    load_frame(argv[1]);
    test_version();
    ctx = new_context();
    test_bit_for_bit(ctx, argv[1]);
    test_layouts(ctx, argv[1]);
    test_errors(ctx);
    test_param_listing(ctx);
    test_prior(ctx);
    test_memory_budget();
    test_cancellation(ctx);
    OK(gdr_context_release(&ctx));
    if (argc > 2) test_frame_and_log(argv[2]);
    /* Not under valgrind: ONNX Runtime's own allocations and a 10x slower network add
     * nothing the Rust tests of the ABI layer do not already cover. */
    if (argc > 2 && !getenv("GDR_TEST_NO_GRADNET")) test_gradnet(argv[2]);
    for (i = 0; i < NLAYERS; i++) free(layers[i]);
    printf("%d passed, %d failed\n", passed, failed);
    return failed ? 1 : 0;
}
