import sys, time, re, subprocess
# rtwatch.py CMD...: runs CMD while sampling CPU 0's rt_rq (rt_time, rt_throttled) every 50 ms
p = subprocess.Popen(sys.argv[1:], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
mx, thr, n = 0.0, 0, 0
while p.poll() is None:
    t = open('/sys/kernel/debug/sched/debug').read()
    m = re.search(r'rt_rq\[0\]:/\n\s+\.rt_nr_running\s+: \d+\n\s+\.rt_throttled\s+: (\d+)\n\s+\.rt_time\s+: ([\d.]+)', t)
    if m:
        n += 1; thr += int(m.group(1)); mx = max(mx, float(m.group(2)))
    time.sleep(0.05)
out = p.stdout.read()
for l in out.splitlines():
    if 'median_us' in l:
        print(re.search(r'"median_us[^,]*,"p99_us[^,]*,"p999_us[^,]*,"max_us[^,]*', l).group(0))
print(f"cpu0 rt_time max {mx:.1f} ms of 950, throttled in {thr} of {n} samples")
