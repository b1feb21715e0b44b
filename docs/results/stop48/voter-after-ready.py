import re, sys, statistics as st
from collections import Counter
exec(open('voter-calls.py').read().split("K=int")[0])
# each fork child's Ready (2nd sendto), then the voter's syscalls until its next `write` (the event)
seqs=[]
for i,(t,pid,c,n,r) in enumerate(ev):
    if n=='sched:sched_process_fork' and 'ballast' in c:
        child=int(re.search(r'child_pid=(\d+)',r).group(1)); k=0; tr=None
        for j in range(i+1,min(len(ev),i+6000)):
            t2,p2,c2,n2,r2=ev[j]
            if p2==child and n2=='raw_syscalls:sys_enter' and r2.startswith('NR 44 '):
                k+=1
                if k==2: tr=t2; jr=j; break
        if tr is None: continue
        s=[]
        for j in range(jr,min(len(ev),jr+400)):
            t2,p2,c2,n2,r2=ev[j]
            if 'voter' in c2 and n2=='raw_syscalls:sys_enter':
                nr=int(re.search(r'NR (\d+)',r2).group(1)); s.append((names.get(nr,nr),t2-tr))
                if nr==1: break
        seqs.append(s)
print(Counter(tuple(x for x,_ in s) for s in seqs).most_common(3))
L=Counter(len(s) for s in seqs).most_common(1)[0][0]
g=[s for s in seqs if len(s)==L]
for k in range(L): print("  %-20s %6.1f"%(g[0][k][0],st.median(s[k][1] for s in g)))
