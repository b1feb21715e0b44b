#!/usr/bin/env python3
"""Restart timeline from `perf script` output (see trace.sh). Per fork of a replica: RESTART sent
(voter's pidfd_send_signal) -> donor handler (signal_deliver sig 10) -> fork -> child's Hello
(first sendto) -> mlockall -> recvmsg -> Ready (second sendto); the child's page faults before
Ready, by kind (ifetch / read / write)."""
import re, sys, statistics as st
ev = []
pat = re.compile(r'^\s*(\S.*?)\s+(\d+)\s+\[(\d+)\]\s+([\d.]+):\s+(\S+):\s*(.*)$')
for line in open(sys.argv[1]):
    m = pat.match(line)
    if not m: continue
    comm, pid, cpu, ts, name, rest = m.groups()
    ev.append((float(ts)*1e6, int(pid), comm, name, rest))
forks = []
for i,(t,pid,comm,name,rest) in enumerate(ev):
    if name == 'sched:sched_process_fork' and 'ballast' in comm:
        c = int(re.search(r'child_pid=(\d+)', rest).group(1))
        forks.append((i, t, pid, c))
rows = []
for (i, tf, donor, child) in forks:
    # backwards: donor's signal_deliver and the voter's RESTART
    tdel = tres = None
    for j in range(i-1, max(0,i-400), -1):
        t,pid,comm,name,rest = ev[j]
        if tdel is None and pid == donor and name == 'signal:signal_deliver' and 'sig=10' in rest:
            tdel = t
        if name == 'syscalls:sys_enter_pidfd_send_signal' and 'voter' in comm:
            tres = t; break
    sends = []; ml = []; rv = []; faults = {'ifetch':0,'read':0,'write':0}; fb = {'ifetch':0,'read':0,'write':0}
    hello = None
    for j in range(i+1, min(len(ev), i+3000)):
        t,pid,comm,name,rest = ev[j]
        if pid != child: continue
        if name == 'syscalls:sys_enter_sendto':
            sends.append(t)
            if hello is None: hello = t
            if len(sends) == 2: break
        elif name.startswith('syscalls:sys_') and 'mlockall' in name: ml.append(t)
        elif name.startswith('syscalls:sys_') and 'recvmsg' in name: rv.append(t)
        elif name == 'exceptions:page_fault_user':
            ec = int(re.search(r'error_code=(0x[0-9a-f]+)', rest).group(1), 16)
            k = 'ifetch' if ec & 0x10 else ('write' if ec & 2 else 'read')
            (fb if hello is None else faults)[k] += 1
    if len(sends) < 2 or tres is None: continue
    rows.append(dict(res_del=(tdel - tres) if tdel else None, del_fork=tf-(tdel or tres), fork_hello=sends[0]-tf,
                     ml=(ml[1]-ml[0]) if len(ml)>=2 else None, hello_ready=sends[1]-sends[0],
                     recv=(rv[1]-rv[0]) if len(rv)>=2 else None, total=sends[1]-tres,
                     fb_i=fb['ifetch'], fb_r=fb['read'], fb_w=fb['write'], f_i=faults['ifetch'], f_r=faults['read'], f_w=faults['write']))
print(f"{len(rows)} forks")
for k in rows[0] if rows else []:
    v = [r[k] for r in rows if r[k] is not None]
    if v: print(f"{k:12s} median {st.median(v):8.1f}  min {min(v):8.1f}  max {max(v):8.1f}")
# where fork -> Hello goes: the donor's switch out, the child's first switch in
sw = []
for (i, tf, donor, child) in forks:
    tout = tin = None; nxt = None
    for j in range(i+1, min(len(ev), i+3000)):
        t,pid,comm,name,rest = ev[j]
        if name != 'sched:sched_switch': continue
        m = re.search(r'prev_pid=(\d+).*next_comm=(.*?) next_pid=(\d+)', rest)
        pp, nc, np_ = int(m.group(1)), m.group(2), int(m.group(3))
        if pp == donor and tout is None: tout = t; nxt = nc
        if np_ == child: tin = t; break
    if tout and tin: sw.append((tout - tf, tin - tf, nxt))
if sw:
    print("fork -> donor switched out: median %.1f; fork -> child switched in: median %.1f" % (st.median([a for a,_,_ in sw]), st.median([b for _,b,_ in sw])))
    from collections import Counter; print(Counter(n for _,_,n in sw).most_common(4))
# the donor between the handler's start and the fork
seg = []
for (i, tf, donor, child) in forks:
    tdel = None
    for j in range(i-1, max(0,i-400), -1):
        t,pid,comm,name,rest = ev[j]
        if pid == donor and name == 'signal:signal_deliver': tdel = t; break
    if tdel is None: continue
    marks = [(ev[j][0]-tdel, ev[j][3].split(':')[1].replace('sys_enter_',''), ev[j][4][:40]) for j in range(i-1, max(0,i-400), -1) if ev[j][1] == donor and ev[j][0] >= tdel]
    seg.append(sorted(marks))
if seg:
    n = min(len(s) for s in seg); print("donor, from signal_deliver (µs), medians:")
    for k in range(n):
        print("  %-22s %7.1f" % (seg[0][k][1], st.median([s[k][0] for s in seg if len(s) > k])))
    print("  fork tracepoint       %7.1f" % st.median([tf - (tf - 0) for _ in [0]]) if False else "")
