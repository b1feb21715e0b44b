#!/usr/bin/env python3
# per fork: fork -> Hello (1st sendto) -> mlockall enter/exit -> madvise span -> recvmsg enter/exit -> Ready (2nd sendto); voter's sendmsg (pipes)
import re, sys, statistics as st
pat = re.compile(r'^\s*(\S.*?)\s+(\d+)\s+\[(\d+)\]\s+([\d.]+):\s+(\S+):\s*(.*)$')
ev=[]
for line in open(sys.argv[1]):
    m=pat.match(line)
    if m:
        comm,pid,cpu,ts,name,rest=m.groups(); ev.append((float(ts)*1e6,int(pid),comm,name,rest))
rows=[]
for i,(t,pid,comm,name,rest) in enumerate(ev):
    if name!='sched:sched_process_fork' or 'ballast' not in comm: continue
    child=int(re.search(r'child_pid=(\d+)',rest).group(1))
    d={'fork':t}
    for j in range(i+1,min(len(ev),i+4000)):
        tj,p,c,n,r=ev[j]
        if 'voter' in c and n=='syscalls:sys_enter_sendmsg' and 'hello' in d and 'vsend' not in d: d['vsend']=tj
        if p!=child: continue
        if n=='syscalls:sys_enter_sendto':
            if 'hello' not in d: d['hello']=tj
            else: d['ready']=tj; break
        elif n=='syscalls:sys_enter_mlockall': d.setdefault('ml0',tj)
        elif n=='syscalls:sys_exit_mlockall': d['ml1']=tj
        elif n=='syscalls:sys_enter_madvise': d.setdefault('mad0',tj)
        elif n=='syscalls:sys_exit_madvise': d['mad1']=tj
        elif n=='syscalls:sys_enter_recvmsg': d.setdefault('rv0',tj)
        elif n=='syscalls:sys_exit_recvmsg': d.setdefault('rv1',tj)
    if 'ready' in d: rows.append(d)
keys=['hello','ml0','ml1','mad0','mad1','rv0','rv1','vsend','ready']
print(len(rows),'forks; medians, µs after the fork:')
for k in keys:
    v=[r[k]-r['fork'] for r in rows if k in r]
    if v: print(f'  {k:6s} {st.median(v):7.1f}  (n={len(v)})')
ml=[r['ml1']-r['ml0'] for r in rows if 'ml1' in r and 'ml0' in r]
print('  mlockall calls span', round(st.median(ml),1))
rw=[r['rv1']-r['rv0'] for r in rows if 'rv1' in r]
print('  recvmsg wait', round(st.median(rw),1))
