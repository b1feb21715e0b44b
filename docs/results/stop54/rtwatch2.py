import sys, time, re, subprocess
# rtwatch2.py CMD...: runs CMD while sampling both CPUs' rt_rq (rt_time, rt_throttled) every 20 ms
# (debugfs: mount -t debugfs none /sys/kernel/debug); prints each CPU's max rt_time, the samples
# that found it throttled, and when (seconds from the start).
p = subprocess.Popen(sys.argv[1:], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
t0 = time.monotonic()
mx, thr, n, when = [0.0, 0.0], [0, 0], 0, [[], []]
pat = [re.compile(r'rt_rq\[%d\]:/\n\s+\.rt_nr_running\s+: \d+\n\s+\.rt_throttled\s+: (\d+)\n\s+\.rt_time\s+: ([\d.]+)' % c) for c in (0, 1)]
while p.poll() is None:
    t = open('/sys/kernel/debug/sched/debug').read()
    n += 1
    for c in (0, 1):
        m = pat[c].search(t)
        if m:
            if int(m.group(1)):
                thr[c] += 1; when[c].append(round(time.monotonic() - t0, 2))
            mx[c] = max(mx[c], float(m.group(2)))
    time.sleep(0.02)
out = p.stdout.read()
for l in out.splitlines():
    if 'median_us' in l:
        print(re.search(r'"median_us[^,]*,"p99_us[^,]*,"p999_us[^,]*,"max_us[^,]*', l).group(0))
for c in (0, 1):
    print(f"cpu{c} rt_time max {mx[c]:.1f} ms of 950, throttled in {thr[c]} of {n} samples {when[c][:20]}")
