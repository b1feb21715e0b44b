// A C++ component through the same header (it is extern "C"): an echo that owns its ports
// with unique_ptr. Run by tests/c_abi.rs in standalone mode (input "in" is stdin, output
// "out" is stdout), linked against the shared library.
#include <cstdio>
#include <memory>

#include "s3res.h"

namespace {

struct InClose {
    void operator()(s3res_in *p) const { s3res_in_close(p); }
};
struct OutClose {
    void operator()(s3res_out *p) const { s3res_out_close(p); }
};
struct RuntimeFree {
    void operator()(s3res_runtime *p) const { s3res_runtime_free(p); }
};

int fail(const char *what) {
    std::fprintf(stderr, "Error: %s: %s\n", what, s3res_last_error());
    return 1;
}

}  // namespace

int main() {
    s3res_init_logging("cxx-echo");
    s3res_runtime *raw_rt = nullptr;
    if (s3res_init(&raw_rt) < 0) return fail("init");
    std::unique_ptr<s3res_runtime, RuntimeFree> rt(raw_rt);
    if (s3res_mode(rt.get()) != S3RES_MODE_STANDALONE) return fail("mode");

    s3res_in *raw_in = nullptr;
    s3res_out *raw_out = nullptr;
    if (s3res_input(rt.get(), "in", &raw_in) < 0) return fail("input");
    std::unique_ptr<s3res_in, InClose> in(raw_in);
    if (s3res_output(rt.get(), "out", &raw_out) < 0) return fail("output");
    std::unique_ptr<s3res_out, OutClose> out(raw_out);

    const uint8_t *frame = nullptr;
    size_t len = 0;
    int rc;
    while ((rc = s3res_recv(in.get(), &frame, &len)) > 0) {
        if (s3res_send(out.get(), frame, len) < 0) return fail("send");
    }
    return rc < 0 ? fail("recv") : 0;
}
