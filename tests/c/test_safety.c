/* Misuse of the gdrecon C API by a renderer's process (issue #18), compiled as C99 and run by
 * tests/c/run.sh, also under valgrind:
 *   test_safety
 * Each case must end in its documented status: no abort, no use after free, nothing printed by
 * the library (stderr is captured around the calls that panic and must stay empty), calls to
 * the log callback never overlap. Needs the library built with the `testing` feature
 * (internal_test_panic). The last line is "N passed, N failed". Set GDR_TEST_NO_TIMING=1 to
 * skip the timed cases (valgrind). */
#define _POSIX_C_SOURCE 200809L
#include <pthread.h>
#include <signal.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <sys/types.h>
#include <sys/wait.h>
#include <time.h>
#include <unistd.h>

#include "check.h"
#include "gdrecon.h"

static double now_seconds(void) {
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return (double)t.tv_sec + 1e-9 * (double)t.tv_nsec;
}

static void sleep_ms(long ms) {
    struct timespec t;
    t.tv_sec = ms / 1000;
    t.tv_nsec = (ms % 1000) * 1000000L;
    nanosleep(&t, NULL);
}

/* ---- a small frame ------------------------------------------------------------------- */

enum { W = 48, H = 32, N = W * H * 3 };
static float color[N], dx[N], dy[N], out[N];

static void make_frame(void) {
    int x, y, c;
    for (y = 0; y < H; y++)
        for (x = 0; x < W; x++)
            for (c = 0; c < 3; c++) {
                int p = (y * W + x) * 3 + c;
                color[p] = 0.25f + 0.01f * (float)((x * 7 + y * 3 + c) % 17);
                dx[p] = x + 1 < W ? 0.01f : 0.0f;
                dy[p] = y + 1 < H ? -0.01f : 0.0f;
            }
}

static gdr_context* new_context(gdr_log_fn log, void* user, int level) {
    gdr_context* ctx = NULL;
    OK(gdr_context_new(&ctx));
    OK(gdr_context_set_int(ctx, "threads", 2));
    if (log) OK(gdr_context_set_log_callback(ctx, log, user));
    OK(gdr_context_set_int(ctx, "log_level", level));
    OK(gdr_context_commit(ctx));
    return ctx;
}

static gdr_filter* new_filter(gdr_context* ctx, const char* method) {
    gdr_filter* f = NULL;
    OK(gdr_filter_new(ctx, method, &f));
    OK(gdr_filter_set_image(f, "color", color, W, H, 3, 0, 0));
    OK(gdr_filter_set_image(f, "dx", dx, W, H, 3, 0, 0));
    OK(gdr_filter_set_image(f, "dy", dy, W, H, 3, 0, 0));
    OK(gdr_filter_set_image(f, "output", out, W, H, 3, 0, 0));
    OK(gdr_filter_commit(f));
    return f;
}

/* ---- stderr capture ------------------------------------------------------------------ */

static int saved_stderr = -1;
static char capture_path[64];

static void capture_stderr(void) {
    int fd;
    fflush(stderr);
    strcpy(capture_path, "/tmp/gdr_test_stderr_XXXXXX");
    fd = mkstemp(capture_path);
    saved_stderr = dup(2);
    dup2(fd, 2);
    close(fd);
}

/* Restores stderr; returns how many bytes were written to it meanwhile (and shows them). */
static long captured_bytes(void) {
    struct stat st;
    long size = -1;
    fflush(stderr);
    dup2(saved_stderr, 2);
    close(saved_stderr);
    if (stat(capture_path, &st) == 0) size = (long)st.st_size;
    if (size > 0) {
        char buf[512];
        FILE* f = fopen(capture_path, "r");
        size_t n = f ? fread(buf, 1, sizeof buf - 1, f) : 0;
        buf[n] = '\0';
        if (f) fclose(f);
        fprintf(stderr, "the library wrote to stderr: %s\n", buf);
    }
    unlink(capture_path);
    return size;
}

/* ---- logging ------------------------------------------------------------------------- */

struct log_record {
    int lines[5];
    char last_error[512];
    char last_info[512];
};

static void record_log(void* user, uint32_t level, const char* message) {
    struct log_record* r = (struct log_record*)user;
    if (level >= 5) return;
    r->lines[level]++;
    if (level == GDR_LOG_ERROR) strncpy(r->last_error, message, sizeof r->last_error - 1);
    if (level == GDR_LOG_INFO) strncpy(r->last_info, message, sizeof r->last_info - 1);
}

/* Every failure of a function that has a context is logged; a cancel at GDR_LOG_INFO. */
static bool cancel_now(void* user, double fraction) {
    (void)user;
    (void)fraction;
    return false;
}

static void test_failures_are_logged(void) {
    struct log_record r;
    gdr_context* ctx;
    gdr_filter* f = NULL;
    memset(&r, 0, sizeof r);
    ctx = new_context(record_log, &r, GDR_LOG_INFO);
    EXPECT(gdr_filter_new(ctx, "gradnot", &f), GDR_ERROR_INVALID_ARGUMENT);
    CHECK(r.lines[GDR_LOG_ERROR] == 1);
    CONTAINS(r.last_error, "gdr_filter_new");
    CONTAINS(r.last_error, "gradnot");
    EXPECT(gdr_context_set_int(ctx, "threads", 3), GDR_ERROR_INVALID_OPERATION);
    CHECK(r.lines[GDR_LOG_ERROR] == 2);
    CONTAINS(r.last_error, "gdr_context_set_int");
    EXPECT(gdr_context_set_string(ctx, "nope", "x"), GDR_ERROR_INVALID_ARGUMENT);
    EXPECT(gdr_context_get_int(ctx, "nope", NULL), GDR_ERROR_NULL_POINTER);
    EXPECT(gdr_context_commit(ctx), GDR_ERROR_INVALID_OPERATION);
    CHECK(r.lines[GDR_LOG_ERROR] == 5);
    CONTAINS(r.last_error, "gdr_context_commit");
    f = new_filter(ctx, "l1");
    OK(gdr_filter_set_progress_callback(f, cancel_now, NULL));
    r.lines[GDR_LOG_INFO] = 0;
    EXPECT(gdr_filter_execute(f), GDR_ERROR_CANCELLED);
    CHECK(r.lines[GDR_LOG_ERROR] == 5); /* a cancel is not a failure */
    CHECK(r.lines[GDR_LOG_INFO] == 1);
    CONTAINS(r.last_info, "cancel");
    OK(gdr_filter_release(&f));
    OK(gdr_context_release(&ctx));
}

/* A panic inside the library prints nothing; its message reaches the log callback. */
static void test_panics_are_silent(void) {
    struct log_record r;
    gdr_context* ctx;
    gdr_filter* f;
    const char* m;
    memset(&r, 0, sizeof r);
    ctx = new_context(record_log, &r, GDR_LOG_WARNING);
    f = new_filter(ctx, "l2");
    capture_stderr();
    m = EXPECT(gdr_filter_set_bool(f, "internal_test_panic", true), GDR_ERROR_UNKNOWN);
    CHECK(captured_bytes() == 0);
    CONTAINS(m, "deliberate panic");
    CONTAINS(m, "filter.rs"); /* the location, from the panic hook */
    CHECK(r.lines[GDR_LOG_ERROR] == 1);
    CONTAINS(r.last_error, "deliberate panic");
    /* The same on one of the context's pool threads. */
    capture_stderr();
    m = EXPECT(gdr_filter_set_bool(f, "internal_test_panic_in_pool", true), GDR_ERROR_UNKNOWN);
    CHECK(captured_bytes() == 0);
    CONTAINS(m, "internal_test_panic_in_pool");
    CHECK(r.lines[GDR_LOG_ERROR] == 2);
    /* The filter still works. */
    OK(gdr_filter_commit(f));
    OK(gdr_filter_execute(f));
    OK(gdr_filter_release(&f));
    OK(gdr_context_release(&ctx));
}

/* Calls to one context's log callback never overlap, from two threads executing two filters. */
static volatile int log_inside = 0, log_overlaps = 0, log_calls = 0;

static void slow_log(void* user, uint32_t level, const char* message) {
    (void)user;
    (void)level;
    (void)message;
    if (__sync_fetch_and_add(&log_inside, 1) != 0) __sync_fetch_and_add(&log_overlaps, 1);
    __sync_fetch_and_add(&log_calls, 1);
    sleep_ms(2);
    __sync_fetch_and_sub(&log_inside, 1);
}

static void* execute_many(void* arg) {
    gdr_filter* f = (gdr_filter*)arg;
    int i;
    for (i = 0; i < 20; i++) gdr_filter_execute(f);
    return NULL;
}

static void test_log_calls_never_overlap(void) {
    gdr_context* ctx = new_context(slow_log, NULL, GDR_LOG_DEBUG);
    gdr_filter* a = new_filter(ctx, "l2");
    gdr_filter* b = NULL;
    static float out_b[N];
    pthread_t ta, tb;
    OK(gdr_filter_new(ctx, "l2", &b));
    OK(gdr_filter_set_image(b, "color", color, W, H, 3, 0, 0));
    OK(gdr_filter_set_image(b, "dx", dx, W, H, 3, 0, 0));
    OK(gdr_filter_set_image(b, "dy", dy, W, H, 3, 0, 0));
    OK(gdr_filter_set_image(b, "output", out_b, W, H, 3, 0, 0));
    OK(gdr_filter_commit(b));
    log_calls = 0;
    pthread_create(&ta, NULL, execute_many, a);
    pthread_create(&tb, NULL, execute_many, b);
    pthread_join(ta, NULL);
    pthread_join(tb, NULL);
    printf("log callback: %d calls from 2 threads, %d overlapped\n", log_calls, log_overlaps);
    CHECK(log_calls >= 40);
    CHECK(log_overlaps == 0);
    OK(gdr_filter_release(&a));
    OK(gdr_filter_release(&b));
    OK(gdr_context_release(&ctx));
}

/* Removing the callback waits for a running call: afterwards it is never called again. */
static volatile int slow_entered = 0, slow_returned = 0;

static void very_slow_log(void* user, uint32_t level, const char* message) {
    (void)user;
    (void)level;
    (void)message;
    slow_entered = 1;
    sleep_ms(200);
    slow_returned = 1;
}

static void* execute_once(void* arg) {
    gdr_filter_execute((gdr_filter*)arg);
    return NULL;
}

static void test_clearing_the_callback_waits(void) {
    gdr_context* ctx = new_context(NULL, NULL, GDR_LOG_INFO);
    gdr_filter* f = new_filter(ctx, "l2");
    pthread_t t;
    int returned_when_cleared;
    OK(gdr_context_set_log_callback(ctx, very_slow_log, NULL));
    pthread_create(&t, NULL, execute_once, f); /* logs its report at INFO */
    while (!slow_entered) sleep_ms(1);
    OK(gdr_context_set_log_callback(ctx, NULL, NULL));
    returned_when_cleared = slow_returned;
    CHECK(returned_when_cleared == 1);
    pthread_join(t, NULL);
    OK(gdr_filter_release(&f));
    OK(gdr_context_release(&ctx));
}

/* A log callback may call gdr_ functions: on the same context (what they log is dropped),
 * except replacing the callback itself; and it may release the context's last reference. */
struct reentrant_state {
    gdr_context* ctx;
    int calls, level_read;
    gdr_error get, bad_set, replace;
    int release_in_callback;
};

static void reentrant_log(void* user, uint32_t level, const char* message) {
    struct reentrant_state* s = (struct reentrant_state*)user;
    (void)level;
    (void)message;
    s->calls++;
    if (s->release_in_callback) {
        gdr_context_release(&s->ctx); /* the caller's last reference */
        return;
    }
    if (s->calls > 1) return;
    s->get = gdr_context_get_int(s->ctx, "log_level", &s->level_read);
    s->bad_set = gdr_context_set_int(s->ctx, "nope", 1); /* fails, logs: dropped */
    s->replace = gdr_context_set_log_callback(s->ctx, NULL, NULL);
    gdr_get_error(NULL);
}

static void test_reentrant_log_callback(void) {
    struct reentrant_state s;
    gdr_filter* f;
    memset(&s, 0, sizeof s);
    OK(gdr_context_new(&s.ctx));
    OK(gdr_context_set_int(s.ctx, "log_level", GDR_LOG_DEBUG));
    OK(gdr_context_set_log_callback(s.ctx, reentrant_log, &s));
    OK(gdr_context_commit(s.ctx));
    CHECK(s.calls == 1); /* "context committed" */
    CHECK(s.get == GDR_ERROR_NONE && s.level_read == GDR_LOG_DEBUG);
    CHECK(s.bad_set == GDR_ERROR_INVALID_ARGUMENT);
    CHECK(s.replace == GDR_ERROR_INVALID_OPERATION);
    f = new_filter(s.ctx, "l2");
    OK(gdr_filter_execute(f));
    OK(gdr_filter_release(&f));
    OK(gdr_context_release(&s.ctx));
    /* The callback releases the last reference during gdr_context_commit's log call. */
    memset(&s, 0, sizeof s);
    OK(gdr_context_new(&s.ctx));
    OK(gdr_context_set_int(s.ctx, "log_level", GDR_LOG_DEBUG));
    OK(gdr_context_set_log_callback(s.ctx, reentrant_log, &s));
    s.release_in_callback = 1;
    OK(gdr_context_commit(s.ctx));
    CHECK(s.calls == 1 && s.ctx == NULL);
}

/* ---- references ---------------------------------------------------------------------- */

/* A progress callback that releases the filter's last reference: execute keeps its own. */
struct release_state {
    gdr_filter* filter;
    int calls;
};

static bool release_in_progress(void* user, double fraction) {
    struct release_state* s = (struct release_state*)user;
    (void)fraction;
    if (s->calls++ == 0) gdr_filter_release(&s->filter);
    return true;
}

static void test_release_from_progress(void) {
    gdr_context* ctx = new_context(NULL, NULL, GDR_LOG_WARNING);
    struct release_state s;
    gdr_filter* f = new_filter(ctx, "l1");
    s.filter = f;
    s.calls = 0;
    OK(gdr_filter_set_progress_callback(f, release_in_progress, &s));
    OK(gdr_filter_execute(f)); /* the last reference goes while it runs */
    CHECK(s.calls >= 2 && s.filter == NULL);
    OK(gdr_context_release(&ctx));
}

/* ---- cancelling Open Image Denoise ------------------------------------------------------ */

/* The prior's OIDN run stops only between its operations: a cancel returns at once and the
 * operation finishes in the background, on the filter's own buffers. Releasing the filter and
 * the context right after must be safe (valgrind watches), the caller's frame may be freed at
 * once, and a filter cancelled twice must then give the image of an uncancelled run. Skipped
 * when Open Image Denoise is not found, and under valgrind (GDR_TEST_NO_OIDN=1: OIDN's TBB
 * threads spin, and valgrind runs one thread at a time: a 256 x 160 denoise took minutes). */
enum { PW = 256, PH = 160, PN = PW * PH * 3 };

struct prior_frame {
    float *color, *dx, *dy, *out;
};

static struct prior_frame prior_frame_new(void) {
    struct prior_frame p;
    int i;
    p.color = (float*)malloc(sizeof(float) * PN);
    p.dx = (float*)calloc(PN, sizeof(float));
    p.dy = (float*)calloc(PN, sizeof(float));
    p.out = (float*)calloc(PN, sizeof(float));
    for (i = 0; i < PN; i++) p.color[i] = 0.2f + 0.6f * (float)((i * 2654435761u) >> 24) / 255.0f;
    return p;
}

static void prior_frame_free(struct prior_frame* p) {
    free(p->color);
    free(p->dx);
    free(p->dy);
    free(p->out);
}

static gdr_filter* prior_filter(gdr_context* ctx, struct prior_frame* p) {
    gdr_filter* f = NULL;
    OK(gdr_filter_new(ctx, "prior", &f));
    OK(gdr_filter_set_image(f, "color", p->color, PW, PH, 3, 0, 0));
    OK(gdr_filter_set_image(f, "dx", p->dx, PW, PH, 3, 0, 0));
    OK(gdr_filter_set_image(f, "dy", p->dy, PW, PH, 3, 0, 0));
    OK(gdr_filter_set_image(f, "output", p->out, PW, PH, 3, 0, 0));
    OK(gdr_filter_commit(f));
    return f;
}

struct cancel_later {
    gdr_filter* filter;
    long ms;
};

static void* cancel_after(void* arg) {
    struct cancel_later* c = (struct cancel_later*)arg;
    sleep_ms(c->ms);
    gdr_filter_cancel(c->filter);
    return NULL;
}

/* Executes `f` with a cancel `ms` after the start; returns the status. */
static gdr_error execute_cancelled(gdr_filter* f, long ms) {
    pthread_t t;
    struct cancel_later c;
    gdr_error e;
    const char* msg = "";
    c.filter = f;
    c.ms = ms;
    pthread_create(&t, NULL, cancel_after, &c);
    e = gdr_filter_execute(f);
    pthread_join(t, NULL);
    gdr_get_error(&msg); /* a cancel's status is expected: clear it */
    return e;
}

static void test_cancelled_prior_then_release(void) {
    gdr_context* ctx;
    struct prior_frame p, q;
    gdr_filter* f;
    float* want;
    gdr_error e;
    const char* msg = "";
    int i, same = 1;
    if (getenv("GDR_TEST_NO_OIDN")) {
        printf("skipped: the cancelled prior (GDR_TEST_NO_OIDN)\n");
        return;
    }
    ctx = new_context(NULL, NULL, GDR_LOG_WARNING);
    p = prior_frame_new();
    f = prior_filter(ctx, &p);
    want = (float*)malloc(sizeof(float) * PN);
    e = gdr_filter_execute(f);
    if (e != GDR_ERROR_NONE) {
        gdr_get_error(&msg);
        printf("skipped: the prior cannot run here (%s)\n", msg);
        OK(gdr_filter_release(&f));
        OK(gdr_context_release(&ctx));
        prior_frame_free(&p);
        free(want);
        return;
    }
    memcpy(want, p.out, sizeof(float) * PN);
    /* Cancelled twice (the second waits for the first's operation), then run to the end. */
    e = execute_cancelled(f, 5);
    CHECK(e == GDR_ERROR_CANCELLED || e == GDR_ERROR_NONE);
    e = execute_cancelled(f, 5);
    CHECK(e == GDR_ERROR_CANCELLED || e == GDR_ERROR_NONE);
    OK(gdr_filter_execute(f));
    for (i = 0; i < PN; i++) same &= p.out[i] == want[i];
    CHECK(same);
    /* Cancelled, then everything released at once: the frame, the filter, the context. */
    q = prior_frame_new();
    OK(gdr_filter_release(&f));
    f = prior_filter(ctx, &q);
    e = execute_cancelled(f, 5);
    CHECK(e == GDR_ERROR_CANCELLED || e == GDR_ERROR_NONE);
    prior_frame_free(&q);
    OK(gdr_filter_release(&f));
    OK(gdr_context_release(&ctx));
    sleep_ms(300); /* the background operation ends while nothing of it is left */
    prior_frame_free(&p);
    free(want);
}

/* ---- views ---------------------------------------------------------------------------- */

static gdr_filter* views_filter(gdr_context* ctx, uintptr_t in, uintptr_t output, size_t w,
                                size_t h, size_t pixel, size_t row) {
    gdr_filter* f = NULL;
    OK(gdr_filter_new(ctx, "l2", &f));
    OK(gdr_filter_set_image(f, "color", (const float*)in, w, h, 3, pixel, row));
    OK(gdr_filter_set_image(f, "dx", (const float*)(in + 12), w, h, 3, pixel, row));
    OK(gdr_filter_set_image(f, "dy", (const float*)(in + 24), w, h, 3, pixel, row));
    OK(gdr_filter_set_image(f, "output", (const float*)output, w, h, 3, pixel, row));
    return f;
}

/* The overlap check allocates nothing and takes O(rows): views far apart, 100000 x 100000
 * views, a 4K frame whose passes share one buffer re-committed with new pointers. Commit
 * reads no pixel, so the views point at memory that is never touched. */
static void test_overlap_check_is_cheap(void) {
    gdr_context* ctx = new_context(NULL, NULL, GDR_LOG_WARNING);
    const char* no_timing = getenv("GDR_TEST_NO_TIMING");
    uintptr_t base = (uintptr_t)1 << 40;
    gdr_filter* f;
    double t0, t;
    const char* m;
    int i;
    /* Two 2 x 2 views 512 GiB apart: disjoint (the old check allocated the whole span). */
    f = NULL;
    OK(gdr_filter_new(ctx, "l2", &f));
    OK(gdr_filter_set_image(f, "color", color, 2, 2, 3, 0, 0));
    OK(gdr_filter_set_image(f, "dx", dx, 2, 2, 3, 0, 0));
    OK(gdr_filter_set_image(f, "dy", dy, 2, 2, 3, 0, 0));
    OK(gdr_filter_set_image(f, "output", (const float*)((uintptr_t)color + ((uintptr_t)512 << 30)), 2, 2,
                            3, 0, 0));
    OK(gdr_filter_commit(f));
    OK(gdr_filter_release(&f));
    /* 100000 x 100000, four passes in 12-float pixels: the output one float off 'color'. */
    f = views_filter(ctx, base, base + 4, 100000, 100000, 48, 0);
    t0 = now_seconds();
    m = EXPECT(gdr_filter_commit(f), GDR_ERROR_OVERLAP);
    t = now_seconds() - t0;
    CONTAINS(m, "'color'");
    printf("overlap check, 100000 x 100000 passes in one buffer: %.3f ms\n", 1e3 * t);
    if (!no_timing) CHECK(t < 0.05);
    OK(gdr_filter_release(&f));
    if (no_timing) {
        OK(gdr_context_release(&ctx));
        return;
    }
    /* A 4K frame, four passes interleaved per pixel (48-byte pixels), committed once (plans),
     * then re-committed with new pointers (cheap: the overlap check is all it does). */
    f = views_filter(ctx, base, base + 36, 3840, 2160, 48, 0);
    OK(gdr_filter_commit(f));
    t0 = now_seconds();
    for (i = 0; i < 10; i++) {
        uintptr_t b = base + (uintptr_t)(i + 1) * ((uintptr_t)1 << 30);
        OK(gdr_filter_set_image(f, "color", (const float*)b, 3840, 2160, 3, 48, 0));
        OK(gdr_filter_set_image(f, "dx", (const float*)(b + 12), 3840, 2160, 3, 48, 0));
        OK(gdr_filter_set_image(f, "dy", (const float*)(b + 24), 3840, 2160, 3, 48, 0));
        OK(gdr_filter_set_image(f, "output", (const float*)(b + 36), 3840, 2160, 3, 48, 0));
        OK(gdr_filter_commit(f));
    }
    t = (now_seconds() - t0) / 10;
    printf("pointer-only re-commit, 4K passes in one buffer: %.3f ms\n", 1e3 * t);
    CHECK(t < 0.05);
    OK(gdr_filter_release(&f));
    OK(gdr_context_release(&ctx));
}

/* ---- fork ------------------------------------------------------------------------------ */

/* A child forked after commit gets a clear error instead of hanging, and may release. */
static void test_fork_after_commit(void) {
    gdr_context* ctx = new_context(NULL, NULL, GDR_LOG_WARNING);
    gdr_filter* f = new_filter(ctx, "l2");
    pid_t child;
    int status = -1, pipe_fds[2], child_code = -1;
    OK(gdr_filter_execute(f));
    fflush(stdout);
    fflush(stderr);
    CHECK(pipe(pipe_fds) == 0);
    child = fork();
    if (child == 0) {
        gdr_filter* g = NULL;
        const char* msg = "";
        int code = 0;
        gdr_error e;
        alarm(20); /* a hang ends the child with SIGALRM */
        e = gdr_filter_execute(f);
        gdr_get_error(&msg);
        if (e != GDR_ERROR_INVALID_OPERATION || !strstr(msg, "fork")) {
            fprintf(stderr, "fork child: execute gave %s: %s\n", gdr_error_name(e), msg);
            code |= 1;
        }
        if (gdr_filter_commit(f) != GDR_ERROR_INVALID_OPERATION) code |= 4;
        if (gdr_filter_new(ctx, "l2", &g) != GDR_ERROR_INVALID_OPERATION || g) code |= 8;
        gdr_get_error(NULL);
        if (gdr_filter_release(&f) != GDR_ERROR_NONE) code |= 16;
        if (gdr_context_release(&ctx) != GDR_ERROR_NONE) code |= 32;
        /* A new context works in the child. */
        if (gdr_context_new(&ctx) || gdr_context_set_int(ctx, "threads", 1) || gdr_context_commit(ctx)) {
            code |= 64;
        } else {
            int failed_before = failed;
            f = new_filter(ctx, "l2");
            if (gdr_filter_execute(f) != GDR_ERROR_NONE || failed != failed_before) code |= 128;
            gdr_filter_release(&f);
            gdr_context_release(&ctx);
        }
        /* Through a pipe: valgrind's exit status would replace ours (the child leaks what the
         * pool threads that were not copied into it own). */
        if (write(pipe_fds[1], &code, sizeof code) != (ssize_t)sizeof code) code = 255;
        _exit(code);
    }
    CHECK(child > 0);
    close(pipe_fds[1]);
    if (read(pipe_fds[0], &child_code, sizeof child_code) != (ssize_t)sizeof child_code) child_code = -1;
    close(pipe_fds[0]);
    waitpid(child, &status, 0);
    if (child_code != 0 || !WIFEXITED(status))
        fprintf(stderr, "fork child: code %d, exited %d, signal %d\n", child_code, WIFEXITED(status),
                WIFSIGNALED(status) ? WTERMSIG(status) : 0);
    CHECK(child_code == 0 && WIFEXITED(status));
    OK(gdr_filter_execute(f)); /* the parent is unaffected */
    OK(gdr_filter_release(&f));
    OK(gdr_context_release(&ctx));
}

int main(void) {
    make_frame();
    test_failures_are_logged();
    test_panics_are_silent();
    test_log_calls_never_overlap();
    test_clearing_the_callback_waits();
    test_reentrant_log_callback();
    test_release_from_progress();
    test_cancelled_prior_then_release();
    test_overlap_check_is_cheap();
    test_fork_after_commit();
    printf("%d passed, %d failed\n", passed, failed);
    return failed ? 1 : 0;
}
