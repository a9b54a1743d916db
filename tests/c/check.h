/* The C tests' checks (test_capi.c, test_safety.c): counts passes and failures, prints each
 * failure with its line and, for a status, the library's message. Each test ends with
 * "N passed, N failed" (tests/c/run.sh reads that line). */
#ifndef GDRECON_TEST_CHECK_H
#define GDRECON_TEST_CHECK_H

#include <stdio.h>
#include <string.h>

#include "gdrecon.h"

static int passed = 0, failed = 0;

#define CHECK(cond)                                                                  \
    do {                                                                             \
        if (cond) {                                                                  \
            passed++;                                                                \
        } else {                                                                     \
            failed++;                                                                \
            fprintf(stderr, "FAIL %s:%d: %s\n", __FILE__, __LINE__, #cond);          \
        }                                                                            \
    } while (0)

/* Checks a status; on a mismatch prints the library's message. Returns the message of an
 * expected failure ("" on success) in a static buffer. */
static const char* expect_at(gdr_error got, gdr_error want, const char* expr, int line) {
    static char buf[1024];
    const char* msg = "";
    gdr_error last = gdr_get_error(&msg);
    buf[0] = '\0';
    if (got == want && last == want) {
        passed++;
        strncpy(buf, msg, sizeof buf - 1);
        buf[sizeof buf - 1] = '\0';
    } else {
        failed++;
        fprintf(stderr, "FAIL line %d: %s gave %s (last error %s), expected %s: %s\n", line, expr,
                gdr_error_name(got), gdr_error_name(last), gdr_error_name(want), msg);
    }
    return buf;
}
#define EXPECT(call, want) expect_at((call), (want), #call, __LINE__)
#define OK(call) EXPECT(call, GDR_ERROR_NONE)
#define CONTAINS(msg, s) CHECK(strstr((msg), (s)) != NULL)

#endif
