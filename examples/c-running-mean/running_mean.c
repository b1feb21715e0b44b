/*
 * s3res-c-running-mean: answers every sample with how many samples came so far and their mean;
 * the component of docs/writing-a-component.md, in C.
 *
 * Input port `samples`: frames of one f64 (8 bytes, little-endian). Output port `mean`: one
 * frame per sample, a u64 count then the f64 running mean (16 bytes, little-endian).
 *
 * Single-threaded on purpose: a replica is restarted by fork, and fork copies only the thread
 * that takes the restart signal.
 *
 * Build: cc -O2 -I replica-c/include examples/c-running-mean/running_mean.c \
 *          target/release/libs3res_replica_c.a -lpthread -ldl -lm -o s3res-c-running-mean
 */
#include <inttypes.h>
#include <stdint.h>
#include <stdio.h>
#include <string.h>

#include "s3res.h"

/* Little-endian on every host, whatever its byte order. */
static double get_f64_le(const uint8_t *p) {
    uint64_t bits = 0;
    for (int i = 7; i >= 0; i--) bits = bits << 8 | p[i];
    double x;
    memcpy(&x, &bits, sizeof x);
    return x;
}

static void put_u64_le(uint8_t *p, uint64_t v) {
    for (int i = 0; i < 8; i++) p[i] = (uint8_t)(v >> (8 * i));
}

static void put_f64_le(uint8_t *p, double x) {
    uint64_t bits;
    memcpy(&bits, &x, sizeof bits);
    put_u64_le(p, bits);
}

/* Prints what failed and why (stderr, never stdout: it may be a port); exit status 1. */
static int fail(const char *what) {
    fprintf(stderr, "Error: %s: %s\n", what, s3res_last_error());
    return 1;
}

int main(int argc, char **argv) {
    if (argc > 1) {
        /* --help answers before any port is opened; there are no options. */
        int help = strcmp(argv[1], "--help") == 0 || strcmp(argv[1], "-h") == 0;
        fprintf(help ? stdout : stderr,
                "Usage: %s\nAnswers every sample on port `samples` (one f64) with the count "
                "so far and the running mean on port `mean`. Started by s3res-bootstrap: see "
                "docs/writing-a-component.md.\n",
                argv[0]);
        return help ? 0 : 2;
    }
    /* Logs go to stderr, each line prefixed with component and pid. */
    s3res_init_logging("c-running-mean");
    /* Reads the port map and installs the restart and fault-injection signal handlers. */
    s3res_runtime *rt;
    if (s3res_init(&rt) < 0) return fail("starting the s3res runtime");
    s3res_in *samples;
    s3res_out *mean;
    if (s3res_input(rt, "samples", &samples) < 0) return fail("opening port `samples`");
    if (s3res_output(rt, "mean", &mean) < 0) return fail("opening port `mean`");

    /* The component's state: plain variables. A replica forked from a healthy one keeps them. */
    uint64_t count = 0;
    double sum = 0.0;
    const uint8_t *frame;
    size_t len;
    int rc;
    /* s3res_recv gives one whole frame (1), or 0 once the input has ended. */
    while ((rc = s3res_recv(samples, &frame, &len)) > 0) {
        if (len != 8) {
            fprintf(stderr, "Error: a sample frame must be 8 bytes (one f64), got %zu\n", len);
            return 1;
        }
        sum += get_f64_le(frame);
        count += 1;
        /* Exactly one answer per sample: that is what the voter waits for in each round. */
        uint8_t answer[16];
        put_u64_le(answer, count);
        put_f64_le(answer + 8, sum / (double)count);
        if (s3res_send(mean, answer, sizeof answer) < 0) return fail("sending the mean");
    }
    if (rc < 0) return fail("receiving a sample");

    char line[64];
    snprintf(line, sizeof line, "end of input count=%" PRIu64, count);
    s3res_log(S3RES_LOG_INFO, line);
    s3res_in_close(samples);
    s3res_out_close(mean);
    s3res_runtime_free(rt);
    return 0; /* exit 0 */
}
