#!/usr/bin/env python3
"""Feeds N numbers (1, 2, 3, ...) as s3res text frames on fd 3 (its port `out`), HZ a second.

usage: feed.py N HZ   (started by s3res-bootstrap: fd 3 is its output channel)
Used by testkit/tests/unmodified.rs and scripts/voter-restart.py --preload.
"""
import os, struct, sys, time
n, hz = int(sys.argv[1]), float(sys.argv[2])
t0 = time.monotonic()
for k in range(1, n + 1):
    b = str(k).encode()
    os.write(3, struct.pack('<I', len(b)) + b)
    d = t0 + k / hz - time.monotonic()
    if d > 0:
        time.sleep(d)
