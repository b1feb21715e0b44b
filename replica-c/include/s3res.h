/*
 * s3res.h: the s3res replica runtime for C and C++ components.
 *
 * Link with libs3res_replica_c (static: libs3res_replica_c.a plus -lpthread -ldl -lm; shared:
 * -ls3res_replica_c). It is replica-rt behind a C ABI: the same port map, restart-by-fork
 * handler, fault-injection hooks and memory locking that Rust components get. See
 * docs/writing-a-component.md, "C and C++".
 *
 * Rules (the runtime relies on them):
 *   - Single-threaded. A replica is restarted by fork from a signal handler; fork copies only
 *     the thread that took the signal.
 *   - Do not install handlers for SIGUSR1 (restart), SIGUSR2 (SDC injection), signal 36
 *     (control-flow-error injection; glibc's SIGRTMIN+2) or signal 37 (variable injection;
 *     glibc's SIGRTMIN+3); s3res_init installs them. The two are fixed numbers, the same
 *     whichever C library a program is built on. In a replica SIGCHLD is ignored (do not wait for children); SIGPIPE is ignored.
 *   - Files and sockets you hold open are shared with a replacement forked from you (same
 *     open file description, same offset, same connection): move all channel I/O through the
 *     ports, and keep no other stream open across the run.
 *   - Never write to stdout (it may be a port), and flush stdio buffers you use (an unflushed
 *     buffer is copied into a forked replacement and written twice).
 *
 * Errors are negative errno values; s3res_last_error() gives the message. No call ever lets a
 * Rust panic through: one would come back as -ENOTRECOVERABLE.
 *
 * Written by hand; replica-c's tests check it against the library (every function here is
 * exported and called by a test program, every export is declared here, the constants agree).
 */
#ifndef S3RES_H
#define S3RES_H

#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

/* Opaque handles, owned by the caller. */
typedef struct s3res_runtime s3res_runtime;
typedef struct s3res_in s3res_in;
typedef struct s3res_out s3res_out;

/* s3res_mode() */
#define S3RES_MODE_STANDALONE 0  /* by hand: input "in" is stdin, output "out" is stdout */
#define S3RES_MODE_UNPROTECTED 1 /* by s3res-bootstrap, no voter */
#define S3RES_MODE_REPLICA 2     /* one replica of a protected component */

/* s3res_log() levels */
#define S3RES_LOG_ERROR 1
#define S3RES_LOG_WARN 2
#define S3RES_LOG_INFO 3
#define S3RES_LOG_DEBUG 4
#define S3RES_LOG_TRACE 5

/* Timeouts in microseconds; a negative one means no limit. */
#define S3RES_NO_TIMEOUT (-1)

/* ---- errors, version, logging ---------------------------------------------------------- */

/* The message of the last failed call on this thread ("" if none); valid until the next
 * failing call. */
const char *s3res_last_error(void);

/* The library version, e.g. "0.1.0". */
const char *s3res_version(void);

/* Log lines to stderr, filtered by RUST_LOG (default info), prefixed with component, replica
 * and pid. component_default (may be NULL) names the component when not started by s3res.
 * Call before s3res_init; a second call is harmless. */
void s3res_init_logging(const char *component_default);

/* Logs message at level (S3RES_LOG_*) through the runtime's logger. */
void s3res_log(int level, const char *message);

/* ---- the runtime ----------------------------------------------------------------------- */

/* Once per process, first: reads the port map, installs the injection hooks and, in a
 * replica, the restart handler (SIGCHLD ignored, memory locked with mlockall); ignores
 * SIGPIPE. 0 and *rt set, or -EALREADY, -EINVAL (bad port map), -ENAMETOOLONG, -errno. */
int s3res_init(s3res_runtime **rt);

/* Frees the runtime; ports taken from it stay usable. NULL is ignored. */
void s3res_runtime_free(s3res_runtime *rt);

/* S3RES_MODE_*, or -EINVAL. */
int s3res_mode(const s3res_runtime *rt);

/* The replica number (S3RES_REPLICA) as read at s3res_init, or -1 when not a replica. A
 * replica forked from a donor to replace a faulty one is a copy of the donor's memory and keeps
 * the DONOR's number (and its environment's S3RES_REPLICA), not the slot it now fills: do not
 * use it to name a replica in logs or to pick per-replica behaviour that must follow the slot
 * (the voter's [component#slot pid N] prefix on every stderr line gives the slot). */
int s3res_replica_index(const s3res_runtime *rt);

/* Take a port by the name the system description uses (each once). 0 and *port set, or
 * -ENOENT (no such port; the message lists the ports there are), -EBUSY (already taken),
 * -EBADF (its fd is not open for that direction), -EINVAL. */
int s3res_input(s3res_runtime *rt, const char *name, s3res_in **port);
int s3res_output(s3res_runtime *rt, const char *name, s3res_out **port);

/* Close a port (closing an output ends the stream downstream). NULL is ignored. */
void s3res_in_close(s3res_in *port);
void s3res_out_close(s3res_out *port);

/* ---- frames ---------------------------------------------------------------------------- */

/* The next whole frame, blocking. 1: *payload and *len set; the payload belongs to the port
 * and is valid until its next receive or close, and is aligned as malloc's memory is (16
 * bytes; 64 for a payload above 512 bytes), so it may be read as a struct. 0: end of stream
 * (the writer closed the channel; the normal way for a component to end). -EPROTO: a bad frame stream (too large,
 * cut short). -EIO: input frames were lost with a voter that died, so this replica's state
 * is no longer the component's: end (its voter rebuilds it from a sibling). Other -errno:
 * the read failed. */
int s3res_recv(s3res_in *port, const uint8_t **payload, size_t *len);

/* As s3res_recv without blocking: -EAGAIN when no whole frame is there yet. */
int s3res_try_recv(s3res_in *port, const uint8_t **payload, size_t *len);

/* As s3res_recv, waiting at most timeout_us: -EAGAIN when none came whole in time. */
int s3res_recv_timeout(s3res_in *port, int64_t timeout_us, const uint8_t **payload,
                       size_t *len);

/* Waits until one of ports[0..n) (1 <= n <= 32) is ready: a whole frame buffered in it, or its
 * fd readable (data, end of stream, error). Bit i of *ready is set for each ready ports[i];
 * returns how many are ready, 0 when timeout_us passed, or -errno. A ready port may still
 * answer -EAGAIN to s3res_try_recv (part of a frame came): wait again. */
int s3res_wait_any(s3res_in *const *ports, size_t n, int64_t timeout_us, uint32_t *ready);

/* Sends payload[0..len) as one whole frame, blocking until written (a pending SDC injection
 * flips one bit of the copy sent). 0, -EMSGSIZE (above the port's max_frame), -EPIPE (the
 * reader is gone), or -errno. payload may be NULL when len is 0. */
int s3res_send(s3res_out *port, const void *payload, size_t len);

/* ---- port facts ------------------------------------------------------------------------ */

/* The port's fd, for poll() with fds of your own. The number stays the same across a restart
 * (the pipe behind it does not): never dup or close it yourself. -EINVAL for NULL. */
int s3res_in_fd(const s3res_in *port);
int s3res_out_fd(const s3res_out *port);

/* The port's name, valid while the port is open; NULL for NULL. */
const char *s3res_in_name(const s3res_in *port);
const char *s3res_out_name(const s3res_out *port);

/* The largest payload the port carries (its channel's max_frame); 0 for NULL. */
size_t s3res_in_max_frame(const s3res_in *port);
size_t s3res_out_max_frame(const s3res_out *port);

/* Bytes read ahead from the channel but not yet returned as frames; 0 for NULL. */
size_t s3res_in_buffered(const s3res_in *port);

/* 1 if a whole frame is buffered (a receive would not read), 0 if not, -EINVAL for NULL. */
int s3res_in_has_frame(const s3res_in *port);

/* ---- memory and signals ---------------------------------------------------------------- */

/* mlockall(MCL_CURRENT | MCL_FUTURE): every page, populated. s3res_init already locks a
 * replica's memory as the component's lock_memory says (all, the default, the same as this;
 * used: on fault), so calling this under lock_memory "used" populates everything after all.
 * 0 or -errno (-ENOMEM / -EPERM: raise RLIMIT_MEMLOCK or grant CAP_IPC_LOCK). */
int s3res_lock_memory(void);

/* The signals the runtime handles (for injectors and tests; never handle them yourself):
 * restart (SIGUSR1), SDC (SIGUSR2; a sigqueue value picks the bit), control-flow error
 * (signal 36, glibc's SIGRTMIN+2: spin forever), variable injection (signal 37, glibc's
 * SIGRTMIN+3). SIGKILL needs no hook. */
int s3res_signal_restart(void);
int s3res_signal_inject_sdc(void);
int s3res_signal_inject_cfe(void);
int s3res_signal_inject_var(void);

#ifdef __cplusplus
} /* extern "C" */
#endif

#endif /* S3RES_H */
