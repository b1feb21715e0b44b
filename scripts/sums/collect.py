#!/usr/bin/env python3
"""Collects the running sums an unmodified program under s3res answers.

usage: collect.py OUT [SUMMARY EXPECT]   (started by s3res-bootstrap: fd 3 is its input)

Reads s3res frames on fd 3 as the channel protocol says a reader does (docs/architecture.md,
"Channels and frames"): a voter's successor goes on behind `RESUME k` ("the next data frame is
number k"), and a frame numbered below those already taken is a repeat, dropped; `END` ends the
stream. Writes each sum as a line of OUT. With SUMMARY, also checks that sum k is
1 + 2 + ... + k for k = 1..EXPECT and writes the verdict as JSON to SUMMARY.
Used by testkit/tests/unmodified.rs and scripts/voter-restart.py --preload.
"""
import json, os, struct, sys

out = open(sys.argv[1], 'w')
summary, expect = (sys.argv[2], int(sys.argv[3])) if len(sys.argv) > 3 else (None, 0)
buf, taken, number, repeats, breaks, gaps = b'', 0, 0, 0, 0, 0
ended = False
while not ended:
    chunk = os.read(3, 65536)
    if not chunk:
        break
    buf += chunk
    while len(buf) >= 4:
        n = struct.unpack('<I', buf[:4])[0]
        if n == 0x80000001:
            if len(buf) < 12:
                break
            number = struct.unpack('<Q', buf[4:12])[0]
            buf = buf[12:]
            continue
        if n == 0x80000002:
            ended = True
            break
        if n & 0x80000000:
            sys.exit('collect: bad control word %#x' % n)
        if len(buf) < 4 + n:
            break
        if number < taken:
            repeats += 1
        else:
            gaps += number - taken
            taken = number + 1
            text = buf[4:4 + n].decode(errors='replace')
            out.write(text + '\n')
            out.flush()
            if not text.isdigit() or int(text) != taken * (taken + 1) // 2:
                breaks += 1
        number += 1
        buf = buf[4 + n:]
out.close()
if summary:
    ok = taken == expect and breaks == 0 and gaps == 0
    with open(summary, 'w') as f:
        json.dump({"frames": taken, "missing": expect - taken + gaps, "duplicated": repeats,
                   "reordered": 0, "corrupt": 0, "state_breaks": breaks, "ok": ok}, f)
