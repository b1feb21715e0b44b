/*
 * Calls every function of s3res.h (tests/c_abi.rs checks that each declared name appears here)
 * and checks what it answers. Run by tests/c_abi.rs with the port map
 *   in: fd 0 (stdin), max_frame 1024;  out: fd 1 (stdout), max_frame 64;  aux: fd 3 (in)
 * and this conversation on the pipes:
 *   test writes "side" on aux   -> wait_any on (in, aux) names aux alone; we echo it
 *   test writes "one"           -> we check try_recv/recv_timeout find nothing more, echo it
 *   test writes "two" + "three" -> one write; we wait_any, recv_timeout, try_recv, echo both
 *   test closes stdin and aux   -> we see end of stream, send an empty frame, exit 0
 * Any failed check: a message on stderr and exit status 1.
 */
#include <errno.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "s3res.h"

static int failures = 0;

#define CHECK(cond)                                                                        \
    do {                                                                                   \
        if (!(cond)) {                                                                     \
            fprintf(stderr, "abi_check.c:%d: check failed: %s (last error: %s)\n", __LINE__, \
                    #cond, s3res_last_error());                                            \
            failures++;                                                                    \
        }                                                                                  \
    } while (0)

static int frame_is(const uint8_t *p, size_t len, const char *want) {
    return len == strlen(want) && memcmp(p, want, len) == 0;
}

int main(void) {
    const char *version = s3res_version();
    CHECK(version != NULL && strlen(version) > 0);
    s3res_init_logging("abi-check");
    s3res_log(S3RES_LOG_DEBUG, "abi check starting");

    s3res_runtime *rt = NULL;
    CHECK(s3res_init(&rt) == 0);
    if (rt == NULL) return 1;
    s3res_runtime *again = NULL;
    CHECK(s3res_init(&again) == -EALREADY && again == NULL);
    CHECK(strstr(s3res_last_error(), "already") != NULL);
    CHECK(s3res_mode(rt) == S3RES_MODE_UNPROTECTED);
    CHECK(s3res_replica_index(rt) == -1);

    s3res_in *in = NULL;
    s3res_out *out = NULL;
    CHECK(s3res_input(rt, "nope", &in) == -ENOENT);
    CHECK(strstr(s3res_last_error(), "\"in\"") != NULL);
    CHECK(s3res_input(rt, "in", &in) == 0);
    s3res_in *twice = NULL;
    CHECK(s3res_input(rt, "in", &twice) == -EBUSY && twice == NULL);
    CHECK(s3res_output(rt, "out", &out) == 0);
    if (in == NULL || out == NULL) return 1;

    CHECK(s3res_in_fd(in) == 0);
    CHECK(s3res_out_fd(out) == 1);
    CHECK(strcmp(s3res_in_name(in), "in") == 0);
    CHECK(strcmp(s3res_out_name(out), "out") == 0);
    CHECK(s3res_in_max_frame(in) == 1024);
    CHECK(s3res_out_max_frame(out) == 64);
    CHECK(s3res_in_buffered(in) == 0);
    CHECK(s3res_in_has_frame(in) == 0);

    const uint8_t *p;
    size_t len;
    s3res_in *aux = NULL;
    CHECK(s3res_input(rt, "aux", &aux) == 0);
    if (aux == NULL) return 1;
    CHECK(s3res_in_fd(aux) == 3);
    /* "side" on aux, nothing on in until we answer it. */
    uint32_t ready = 0;
    s3res_in *both[2] = {in, aux};
    CHECK(s3res_wait_any(both, 2, S3RES_NO_TIMEOUT, &ready) == 1 && ready == 2);
    CHECK(s3res_recv(aux, &p, &len) == 1 && frame_is(p, len, "side"));
    CHECK(s3res_send(out, p, len) == 0);

    /* "one", then nothing more until we answer it. */
    CHECK(s3res_recv(in, &p, &len) == 1 && frame_is(p, len, "one"));
    uint8_t copy[16];
    memcpy(copy, p, len);
    size_t copy_len = len;
    CHECK(s3res_try_recv(in, &p, &len) == -EAGAIN && p == NULL && len == 0);
    CHECK(s3res_recv_timeout(in, 20000, &p, &len) == -EAGAIN);
    CHECK(s3res_send(out, copy, copy_len) == 0);

    /* "two" and "three", written at once. */
    s3res_in *ports[1] = {in};
    CHECK(s3res_wait_any(ports, 1, S3RES_NO_TIMEOUT, &ready) == 1 && ready == 1);
    CHECK(s3res_wait_any(ports, 0, 0, &ready) == -EINVAL);
    CHECK(s3res_recv_timeout(in, S3RES_NO_TIMEOUT, &p, &len) == 1 && frame_is(p, len, "two"));
    CHECK(s3res_send(out, p, len) == 0);
    CHECK(s3res_in_has_frame(in) == 1);
    CHECK(s3res_in_buffered(in) == 4 + 5);
    CHECK(s3res_try_recv(in, &p, &len) == 1 && frame_is(p, len, "three"));
    CHECK(s3res_send(out, p, len) == 0);

    uint8_t big[65] = {0};
    CHECK(s3res_send(out, big, sizeof big) == -EMSGSIZE);
    CHECK(strstr(s3res_last_error(), "exceeds the port maximum of 64") != NULL);

    /* End of stream: ready, then 0, and it stays so. */
    CHECK(s3res_wait_any(ports, 1, 10000000, &ready) == 1 && ready == 1);
    CHECK(s3res_recv(in, &p, &len) == 0 && p == NULL && len == 0);
    CHECK(s3res_try_recv(in, &p, &len) == 0);
    CHECK(s3res_recv(aux, &p, &len) == 0);
    CHECK(s3res_send(out, NULL, 0) == 0);

    int locked = s3res_lock_memory();
    CHECK(locked == 0 || locked == -ENOMEM || locked == -EPERM);
    CHECK(s3res_signal_restart() == 10);    /* SIGUSR1 */
    CHECK(s3res_signal_inject_sdc() == 12); /* SIGUSR2 */
    CHECK(s3res_signal_inject_cfe() == s3res_signal_inject_var() - 1);

    s3res_in_close(in);
    s3res_in_close(aux);
    s3res_out_close(out);
    s3res_runtime_free(rt);
    s3res_log(S3RES_LOG_INFO, failures ? "abi check FAILED" : "abi check passed");
    return failures ? 1 : 0;
}
