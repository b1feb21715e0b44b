#!/usr/bin/env python3
# per fork of a ballast replica: the child's syscalls (enter->exit) and faults from fork to Ready: two children's sequences, from the middle of the run
import re, sys, statistics as st, collections
from perfscript import events
ev = events(sys.argv[1])
seqs=[]
for i,(t,pid,comm,name,rest,cpu) in enumerate(ev):
    if name!='sched:sched_process_fork' or 'ballast' not in comm: continue
    child=int(re.search(r'child_pid=(\d+)',rest).group(1)); donor=pid
    seq=[]; sends=0; open_=None
    for j in range(i+1,min(len(ev),i+8000)):
        tj,p,c,n,r,cpu2=ev[j]
        if n=='sched:sched_switch':
            if f'next_pid={child} ' in r or r.endswith(f'next_pid={child}'): seq.append((tj-t,'child on cpu'))
            if f'prev_pid={child} ' in r: seq.append((tj-t,'child off cpu'))
            continue
        if p!=child: 
            if p==donor and n=='raw_syscalls:sys_enter': seq.append((tj-t,'donor sc '+re.search(r'NR (\d+)',r).group(1)))
            continue
        if n=='raw_syscalls:sys_enter':
            nr=re.search(r'NR (\d+)',r).group(1); open_=(tj,nr)
            if nr=='44': sends+=1
        elif n=='raw_syscalls:sys_exit' and open_:
            seq.append((open_[0]-t,f'sc {open_[1]} {tj-open_[0]:.1f}')); 
            if open_[1]=='44' and sends==2: break
            open_=None
        elif n=='exceptions:page_fault_user':
            seq.append((tj-t,'pf '+re.search(r'error_code=(0x[0-9a-f]+)',r).group(1)))
    seqs.append(seq)
print(len(seqs),'forks')
for s in seqs[len(seqs)//2:len(seqs)//2+2]:
    for t,what in s: print(f'  {t:7.1f} {what}')
    print()
